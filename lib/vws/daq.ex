defmodule Vws.DAQ do
  @moduledoc """
  The CEC's driver for DAQ #1 (seed §1.3, §2.3.6; PROTOCOLS.md §4): which SCPI commands read the
  sensors and drive the actuators, and how the readings turn into millimetres, newtons and
  switch states. Pure: the VWS_STATUS partition (`Vws.Partitions.VwsStatus`) sends what this
  module builds over `Vws.HPIB` and hands the answers back to it.

  The channel map is the one the plant simulator is wired by, `priv/sims/plant.exs`
  (`Vws.Sim.Plant.Config`): a real DAQ is wired the same way, or configured with its own file.
  Slot 1 channels of kind switch, pot and spare are read in one `MEAS:VOLT:DC?`, gauges in one
  `MEAS:RES?`; slot 2 relays are driven with `ROUT:OPEN`/`ROUT:CLOS` and confirmed with
  `ROUT:CLOS?`.

      iex> daq = Vws.DAQ.new()
      iex> Vws.DAQ.poll_commands(daq)
      [{:meas_volt_dc?, Enum.to_list(101..116)}, {:meas_res?, [117]}]
      iex> volts = [5.0, 0.0, 3.0] ++ List.duplicate(0.0, 13)
      iex> r = Vws.DAQ.readings(daq, [volts, [370.0]])
      iex> {r.values.vise_part_present, r.values.vise_fully_open, r.values.vise_jaw_mm}
      {true, false, 50.0}
      iex> round(r.values.vise_force_n)
      2000
      iex> Vws.DAQ.actuation(daq, vise_open_valve: :open, vise_close_valve: :close)
      {:ok, [{:rout_open, [205]}, {:rout_clos, [206]}, {:rout_clos?, [205, 206]}],
       [{205, false}, {206, true}]}

  ## Options of `new/1`

    * `:channel_map` — a path, or a map merged over the shipped file (default: the shipped file);
    * `:daq` — which unit of the map (default `:daq1`);
    * `:switches` — extra microswitches wired to channels the map calls spare, as
      `[signal: channel]`. The shipped map has no sensor for the gripper changer, so CHANGER_1
      is reported only once `changer1_released: 116` (say) is configured.
  """

  alias Vws.DAQ.Readings
  alias Vws.Sim.Plant.Config

  @overload_at 1.0e37

  @type signal :: atom
  @type action :: :open | :close
  @type t :: %__MODULE__{
          daq: Config.daq(),
          volt_channels: [pos_integer],
          ohm_channels: [pos_integer],
          sensors: %{pos_integer => map},
          actuators: %{signal => pos_integer},
          threshold_volts: float
        }

  defstruct [:daq, :volt_channels, :ohm_channels, :sensors, :actuators, :threshold_volts]

  @doc "A driver for one DAQ of the channel map; see the options above."
  @spec new(keyword) :: t
  def new(opts \\ []) do
    config = Config.load(Keyword.get(opts, :channel_map, Config.default_path()))
    daq = Keyword.get(opts, :daq, :daq1)

    entries = for {{^daq, channel}, entry} <- config.channels, into: %{}, do: {channel, entry}

    entries =
      Enum.reduce(Keyword.get(opts, :switches, []), entries, fn {signal, channel}, acc ->
        case Map.get(acc, channel) do
          %{kind: :spare} ->
            Map.put(acc, channel, %{kind: :switch, signal: signal})

          other ->
            raise ArgumentError,
                  "switch #{inspect(signal)} needs a spare channel, #{channel} is #{inspect(other)}"
        end
      end)

    sensors = Map.reject(entries, fn {_ch, e} -> e.kind == :actuator end)

    by_kind = fn kinds ->
      for {ch, %{kind: kind}} <- sensors, kind in kinds, do: ch
    end

    %__MODULE__{
      daq: daq,
      volt_channels: Enum.sort(by_kind.([:switch, :pot, :spare])),
      ohm_channels: Enum.sort(by_kind.([:gauge])),
      sensors: sensors,
      actuators: for({ch, %{kind: :actuator, signal: s}} <- entries, into: %{}, do: {s, ch}),
      threshold_volts: config.switch.threshold_volts * 1.0
    }
  end

  @doc "The commands of one poll: every voltage channel, then every resistance channel."
  @spec poll_commands(t) :: [Vws.SCPI.command()]
  def poll_commands(%__MODULE__{volt_channels: volts, ohm_channels: ohms}) do
    [{:meas_volt_dc?, volts}, {:meas_res?, ohms}] |> Enum.reject(&match?({_, []}, &1))
  end

  @doc """
  Turns the answers to `poll_commands/1` (one list of readings per command, in order) into
  `t:Vws.DAQ.Readings.t/0`. Options `:seq`, `:requested_at`, `:received_at` are copied in.
  """
  @spec readings(t, [[float]], keyword) :: Readings.t()
  def readings(%__MODULE__{} = daq, answers, opts \\ []) do
    {volts, ohms} =
      case {daq.volt_channels, daq.ohm_channels, answers} do
        {[], _, [o]} -> {[], o}
        {_, [], [v]} -> {v, []}
        {_, _, [v, o]} -> {v, o}
      end

    volts = Map.new(Enum.zip(daq.volt_channels, volts))
    ohms = Map.new(Enum.zip(daq.ohm_channels, ohms))

    values =
      for {ch, %{kind: kind, signal: signal} = entry} <- daq.sensors, kind != :spare, into: %{} do
        reading = if kind == :gauge, do: Map.fetch!(ohms, ch), else: Map.fetch!(volts, ch)
        {signal, value(entry, reading, daq.threshold_volts)}
      end

    channels =
      for {ch, %{kind: kind, signal: signal}} <- daq.sensors,
          kind != :spare,
          into: %{},
          do: {signal, ch}

    %Readings{
      seq: Keyword.get(opts, :seq, 0),
      requested_at: Keyword.get(opts, :requested_at, 0),
      received_at: Keyword.get(opts, :received_at, 0),
      volts: volts,
      ohms: ohms,
      values: values,
      channels: channels
    }
  end

  defp value(_entry, reading, _threshold) when abs(reading) >= @overload_at, do: :open_circuit
  defp value(%{kind: :switch}, volts, threshold), do: volts > threshold
  defp value(%{kind: :pot} = e, volts, _), do: (volts - e.volts_at_zero) / e.volts_per_unit
  defp value(%{kind: :gauge} = e, ohms, _), do: (ohms - e.ohms_at_zero) / e.ohms_per_newton

  @doc "The relay channel of an actuator signal (a channel number passes through if it is one)."
  @spec actuator(t, signal | pos_integer) :: {:ok, pos_integer} | {:error, :unknown_actuator}
  def actuator(%__MODULE__{actuators: actuators}, signal) when is_atom(signal) do
    case Map.fetch(actuators, signal) do
      {:ok, ch} -> {:ok, ch}
      :error -> {:error, :unknown_actuator}
    end
  end

  def actuator(%__MODULE__{actuators: actuators}, channel) when is_integer(channel) do
    if channel in Map.values(actuators), do: {:ok, channel}, else: {:error, :unknown_actuator}
  end

  @doc """
  The commands that set relays (the seed's Hp_act: a channel and open or close), opens first so
  that two solenoids working against each other are never both on, followed by a `ROUT:CLOS?`
  of every channel touched; and the states that query must return.
  """
  @spec actuation(t, [{signal | pos_integer, action}]) ::
          {:ok, [Vws.SCPI.command()], [{pos_integer, boolean}]}
          | {:error, {:unknown_actuator, term}}
  def actuation(%__MODULE__{} = daq, actions) do
    resolved =
      Enum.reduce_while(actions, [], fn {who, action}, acc when action in [:open, :close] ->
        case actuator(daq, who) do
          {:ok, ch} -> {:cont, [{ch, action == :close} | acc]}
          {:error, _} -> {:halt, {:error, {:unknown_actuator, who}}}
        end
      end)

    case resolved do
      {:error, _} = error ->
        error

      [] ->
        {:ok, [], []}

      list ->
        # the last word on a channel wins
        expected = list |> Enum.reverse() |> Map.new() |> Enum.sort()
        opens = for {ch, false} <- expected, do: ch
        closes = for {ch, true} <- expected, do: ch

        commands =
          [
            {:rout_open, opens},
            {:rout_clos, closes},
            {:rout_clos?, Enum.map(expected, &elem(&1, 0))}
          ]
          |> Enum.reject(&match?({_, []}, &1))

        {:ok, commands, expected}
    end
  end

  @doc """
  Compares the `ROUT:CLOS?` answer with the expected states: `:ok`, or the channels that are not
  as commanded.
  """
  @spec check_relays([{pos_integer, boolean}], [boolean]) :: :ok | {:error, [pos_integer]}
  def check_relays(expected, states) do
    wrong = for {{ch, want}, got} <- Enum.zip(expected, states), want != got, do: ch

    if wrong == [] and length(states) == length(expected), do: :ok, else: {:error, wrong}
  end

  @doc """
  `check_relays/2` as a command status says it, for the DAQ named `device`: `:ok`, or
  `{:error, "DAQ #1 RELAY 206 DID NOT CLOSE"}` (the first channel not as commanded).

      iex> Vws.DAQ.confirm_relays([{205, false}, {206, true}], [false, false], "DAQ #1")
      {:error, "DAQ #1 RELAY 206 DID NOT CLOSE"}
  """
  @spec confirm_relays([{pos_integer, boolean}], [boolean], String.t()) ::
          :ok | {:error, String.t()}
  def confirm_relays(expected, states, device) do
    case check_relays(expected, states) do
      :ok ->
        :ok

      {:error, [ch | _]} ->
        {_, want} = List.keyfind(expected, ch, 0)
        {:error, "#{device} RELAY #{ch} DID NOT #{if want, do: "CLOSE", else: "OPEN"}"}

      {:error, []} ->
        {:error, "#{device} RELAYS NOT ALL READ BACK"}
    end
  end
end
