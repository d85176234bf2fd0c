defmodule Vws.Links.DAQ do
  @moduledoc """
  The CEC's driver for DAQ #1 (seed §1.3, §2.3.6; PROTOCOLS.md §4): which SCPI commands read the
  sensors and drive the actuators, and how the readings turn into millimetres, newtons and
  switch states. Pure: the VWS_STATUS partition (`Vws.Partitions.VwsStatus`) sends what this
  module builds over `Vws.Links.HPIB` and hands the answers back to it.

  The channel map is `priv/plant.exs` (`Vws.Links.DAQ.ChannelMap`), the one the plant simulator is
  wired by too: a real DAQ is wired the same way, or configured with its own file.
  Slot 1 channels of kind switch, pot and spare are read in one `MEAS:VOLT:DC?`, gauges in one
  `MEAS:RES?`; slot 2 relays are driven with `ROUT:OPEN`/`ROUT:CLOS` and the whole slot is
  confirmed with `ROUT:CLOS?` (PROTOCOLS.md §4 "Relays are verified whole").

      iex> daq = Vws.Links.DAQ.new()
      iex> Vws.Links.DAQ.poll_commands(daq)
      [{:meas_volt_dc?, Enum.to_list(101..116)}, {:meas_res?, [117]}]
      iex> volts = [5.0, 0.0, 3.0] ++ List.duplicate(0.0, 13)
      iex> r = Vws.Links.DAQ.readings(daq, [volts, [370.0]])
      iex> {r.values.vise_part_present, r.values.vise_fully_open, r.values.vise_jaw_mm}
      {true, false, 50.0}
      iex> round(r.values.vise_force_n)
      2000
      iex> slot = Vws.Links.DAQ.slot(daq)
      iex> {:ok, commands, expected} =
      ...>   Vws.Links.DAQ.actuation(daq, vise_open_valve: :open, vise_close_valve: :close)
      iex> commands
      [{:rout_clos?, slot}, {:rout_clos?, slot}]
      iex> expected
      {:before, slot, [{205, false}, {206, true}]}
      iex> before = Enum.map(slot, &(&1 == 207))
      iex> {:next, writes, {:whole, _}} =
      ...>   Vws.Links.DAQ.confirm_relays(expected, [before, before], "DAQ #1")
      iex> writes
      [{:rout_open, [205]}, {:rout_clos, [206]}, {:rout_clos?, slot}]

  ## Options of `new/1`

    * `:channel_map` — a path, or a map merged over the shipped file (default: the shipped file);
    * `:daq` — which unit of the map (default `:daq1`);
    * `:switches` — extra microswitches wired to channels the map calls spare, as
      `[signal: channel]`. The shipped map has no sensor for the gripper changer, so CHANGER_1
      is reported only once `changer1_released: 116` (say) is configured.
  """

  alias Vws.Links.DAQ.Readings
  alias Vws.Links.DAQ.ChannelMap

  @overload_at 1.0e37

  @type signal :: atom
  @type action :: :open | :close
  @type t :: %__MODULE__{
          daq: ChannelMap.daq(),
          volt_channels: [pos_integer],
          ohm_channels: [pos_integer],
          sensors: %{pos_integer => map},
          actuators: %{signal => pos_integer},
          threshold_volts: float,
          signal_channels: %{signal => pos_integer},
          layout: {[{pos_integer, map}], [{pos_integer, map}]}
        }

  defstruct [
    :daq,
    :volt_channels,
    :ohm_channels,
    :sensors,
    :actuators,
    :threshold_volts,
    :signal_channels,
    :layout
  ]

  @schema [
    channel_map: [type: {:custom, &__MODULE__.__channel_map__/1}],
    daq: [type: {:in, [:daq1, :daq2]}, default: :daq1],
    switches: [type: :keyword_list, default: []]
  ]

  @doc """
  A driver for one DAQ of the channel map; see the options above. Raises `Vws.Options.Error`
  for an unknown option or a bad value.
  """
  @spec new(keyword) :: t
  def new(opts \\ []) do
    opts = Vws.Options.validate!(opts, @schema, "DAQ")
    config = ChannelMap.load(Keyword.get(opts, :channel_map, ChannelMap.default_path()))
    daq = Keyword.fetch!(opts, :daq)

    entries = for {{^daq, channel}, entry} <- config.channels, into: %{}, do: {channel, entry}

    entries =
      Enum.reduce(Keyword.fetch!(opts, :switches), entries, fn {signal, channel}, acc ->
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

    volt_channels = Enum.sort(by_kind.([:switch, :pot, :spare]))
    ohm_channels = Enum.sort(by_kind.([:gauge]))

    %__MODULE__{
      daq: daq,
      volt_channels: volt_channels,
      ohm_channels: ohm_channels,
      # each answer's channels in order with their map entries: a poll's answers are read in
      # one walk each (readings/3), not looked up channel by channel
      layout: {
        Enum.map(volt_channels, &{&1, Map.fetch!(sensors, &1)}),
        Enum.map(ohm_channels, &{&1, Map.fetch!(sensors, &1)})
      },
      sensors: sensors,
      actuators: for({ch, %{kind: :actuator, signal: s}} <- entries, into: %{}, do: {s, ch}),
      threshold_volts: config.switch.threshold_volts * 1.0,
      # every reading carries it (Readings.channels): built once, not at every poll
      signal_channels:
        for(
          {ch, %{kind: kind, signal: signal}} <- sensors,
          kind != :spare,
          into: %{},
          do: {signal, ch}
        )
    }
  end

  @doc "The commands of one poll: every voltage channel, then every resistance channel."
  @spec poll_commands(t) :: [Vws.Codecs.SCPI.command()]
  def poll_commands(%__MODULE__{volt_channels: volts, ohm_channels: ohms}) do
    [{:meas_volt_dc?, volts}, {:meas_res?, ohms}] |> Enum.reject(&match?({_, []}, &1))
  end

  @doc """
  Turns the answers to `poll_commands/1` (one list of readings per command, in order) into
  `t:Vws.Links.DAQ.Readings.t/0`. Options `:seq`, `:requested_at`, `:received_at` are copied in.
  """
  @spec readings(t, [[float]], keyword) :: Readings.t()
  def readings(%__MODULE__{} = daq, answers, opts \\ []) do
    {volts, ohms} =
      case {daq.volt_channels, daq.ohm_channels, answers} do
        {[], _, [o]} -> {[], o}
        {_, [], [v]} -> {v, []}
        {_, _, [v, o]} -> {v, o}
      end

    {volt_layout, ohm_layout} = daq.layout
    {volts, values} = read(volt_layout, volts, daq.threshold_volts, [], [])
    {ohms, values} = read(ohm_layout, ohms, daq.threshold_volts, [], values)
    volts = :maps.from_list(volts)
    ohms = :maps.from_list(ohms)
    values = :maps.from_list(values)

    %Readings{
      seq: Keyword.get(opts, :seq, 0),
      requested_at: Keyword.get(opts, :requested_at, 0),
      received_at: Keyword.get(opts, :received_at, 0),
      volts: volts,
      ohms: ohms,
      values: values,
      channels: daq.signal_channels
    }
  end

  # One answer against its channels, in order: `{[{channel, reading}], values}`, the values of
  # its sensors (spare channels have none) added to `values`. An answer with more or fewer
  # readings than channels raises, as the HPIB never hands one over (Vws.Codecs.SCPI checks).
  defp read([{ch, entry} | layout], [reading | rest], threshold, raw, values) do
    values =
      case entry do
        %{kind: :spare} -> values
        %{signal: signal} -> [{signal, value(entry, reading, threshold)} | values]
      end

    read(layout, rest, threshold, [{ch, reading} | raw], values)
  end

  defp read([], [], _threshold, raw, values), do: {raw, values}

  @doc false
  def __channel_map__(map_or_path) when is_map(map_or_path) or is_binary(map_or_path),
    do: {:ok, map_or_path}

  def __channel_map__(_), do: {:error, "expected a path or a map"}

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
  Every relay of the slot as wired (the actuator channels of the map), ascending: what a
  whole-slot read-back asks (PROTOCOLS.md §4 "Relays are verified whole").
  """
  @spec slot(t) :: [pos_integer]
  def slot(%__MODULE__{actuators: actuators}), do: actuators |> Map.values() |> Enum.sort()

  @typedoc """
  What a relay transaction must leave behind: `{:before, slot, commanded}` for the reads that
  come before a write (two reads of the whole slot that must agree: they tell what the relays
  the write does not command are), or `{:whole, [{channel, closed?}]}` for a write of the whole
  slot's intended state and any correction of it.
  """
  @type expected ::
          {:before, [pos_integer], [{pos_integer, boolean}]}
          | {:whole, [{pos_integer, boolean}]}

  @doc """
  The commands that set relays (the seed's Hp_act: a channel and open or close), in two
  transactions. The first reads the whole slot twice (the reads must agree: they tell what the
  other relays are) and writes nothing; `confirm_relays/3` then answers `{:next, commands,
  expected}`, the second: the writes, opens first so that two solenoids working against each
  other are never both on, and one read of the whole slot after them (PROTOCOLS.md §4: SCPI has
  no check, so one bit can turn `ROUT:CLOS (@207)` into `(@206)`).

  Two transactions, not one, so that the slot before a write is never lost with the write's
  answers: taking reads made after a damaged write for the slot before it would take a relay
  that write set wrongly (206 for 207) for one meant to be so, and confirm it.
  Returns the first transaction's commands and what `confirm_relays/3` checks.
  """
  @spec actuation(t, [{signal | pos_integer, action}]) ::
          {:ok, [Vws.Codecs.SCPI.command()], expected | []}
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
        commanded = list |> Enum.reverse() |> Map.new() |> Enum.sort()
        slot = slot(daq)
        query = {:rout_clos?, slot}
        {:ok, [query, query], {:before, slot, commanded}}
    end
  end

  defp writes(states) do
    opens = for {ch, false} <- states, do: ch
    closes = for {ch, true} <- states, do: ch
    Enum.reject([{:rout_open, opens}, {:rout_clos, closes}], &match?({_, []}, &1))
  end

  @doc """
  The whole slot a write intends, from the answers of the reads before it: the commanded relays
  as commanded, every other one as both reads found it. `:unknown` when the two reads disagree on
  a relay the write does not command (one was damaged: nothing can be said).
  """
  @spec intended(expected, [term]) :: {:ok, [{pos_integer, boolean}]} | :unknown
  def intended({:whole, states}, _results), do: {:ok, states}

  def intended({:before, slot, commanded}, [before1, before2 | _])
      when is_list(before1) and is_list(before2) and length(before1) == length(slot) and
             length(before2) == length(slot) do
    commanded = Map.new(commanded)

    Enum.zip([slot, before1, before2])
    |> Enum.reduce_while([], fn {ch, b1, b2}, acc ->
      case Map.fetch(commanded, ch) do
        {:ok, want} -> {:cont, [{ch, want} | acc]}
        :error when b1 == b2 -> {:cont, [{ch, b1} | acc]}
        :error -> {:halt, :unknown}
      end
    end)
    |> case do
      :unknown -> :unknown
      list -> {:ok, Enum.reverse(list)}
    end
  end

  def intended(_expected, _results), do: :unknown

  @doc """
  Compares the read-back of the whole slot (the transaction's last answer) with the state
  intended for it: `:ok`, or `{:error, channels}` — the channels not as intended (`[]` when the
  answer is missing or the reads before the write disagree).
  """
  @spec check_relays(expected, [term]) :: :ok | {:error, [pos_integer]}
  # (reads before a write confirm nothing)
  def check_relays({:before, _slot, _commanded}, _results), do: {:error, []}

  def check_relays(expected, results) do
    with {:ok, states} <- intended(expected, results),
         after_write when is_list(after_write) <- List.last(results),
         true <- length(after_write) == length(states) do
      wrong = for {{ch, want}, got} <- Enum.zip(states, after_write), want != got, do: ch
      if wrong == [], do: :ok, else: {:error, wrong}
    else
      _ -> {:error, []}
    end
  end

  @doc """
  `check_relays/2` as a command status says it: `:ok`, or
  `{:error, "RELAY 206 NOT AS COMMANDED"}` (the first channel of the slot not as intended —
  the commanded one or any other), or `RELAYS NOT READ BACK` when the slot could not be read
  back alike. `device` names the DAQ in the latter.

  After the reads before a write (`{:before, …}`), when they agree: `{:next, commands,
  expected}`, the transaction that writes and reads the slot back, and what it must leave.

      iex> Vws.Links.DAQ.confirm_relays({:whole, [{205, false}, {206, true}]}, [:ok, [false, false]], "DAQ #1")
      {:error, "RELAY 206 NOT AS COMMANDED"}
  """
  @spec confirm_relays(expected, [term], String.t()) ::
          :ok | {:next, [Vws.Codecs.SCPI.command()], expected} | {:error, String.t()}
  def confirm_relays({:before, slot, commanded} = expected, results, device) do
    case intended(expected, results) do
      {:ok, states} -> {:next, writes(commanded) ++ [{:rout_clos?, slot}], {:whole, states}}
      :unknown -> {:error, "#{device} RELAYS NOT READ BACK"}
    end
  end

  def confirm_relays(expected, results, device) do
    case check_relays(expected, results) do
      :ok -> :ok
      {:error, [ch | _]} -> {:error, "RELAY #{ch} NOT AS COMMANDED"}
      {:error, []} -> {:error, "#{device} RELAYS NOT READ BACK"}
    end
  end

  @doc """
  After a write that did not read back as intended: the transaction that sets the wrong
  relays right (opens first) and reads the whole slot back, and what it must leave. When the
  read-back is missing, or the intended state is unknown (the reads before the write
  disagreed), the slot is read again first (`recheck/1`), never written blindly.
  """
  @spec correction(expected, [term]) :: {:ok, [Vws.Codecs.SCPI.command()], expected}
  def correction(expected, results) do
    case {intended(expected, results), List.last(results)} do
      {{:ok, states}, after_write}
      when is_list(after_write) and length(after_write) == length(states) ->
        wrong =
          for {{ch, want}, got} <- Enum.zip(states, after_write), want != got, do: {ch, want}

        query = {:rout_clos?, Enum.map(states, &elem(&1, 0))}
        {:ok, writes(wrong) ++ [query], {:whole, states}}

      {{:ok, states}, _no_answer} ->
        # the reads before were good: the slot read again is held against them, whole
        {:ok, recheck({:whole, states}), {:whole, states}}

      {:unknown, _} ->
        {:ok, recheck(expected), expected}
    end
  end

  @doc """
  After a transaction whose answers were damaged or missing: the reads that tell whether its
  writes took effect — once, held against the whole slot `expected` — or, for the reads before a
  write (nothing was written), those reads again. Nothing is written again blindly: a relay is
  set again only by a `correction/2` of these reads, so a write that reached the DAQ while its
  answer was lost is never repeated; and the slot before a write is always the one read before
  it (`actuation/2`).

      iex> Vws.Links.DAQ.recheck({:whole, [{205, false}, {206, true}]})
      [{:rout_clos?, [205, 206]}]
  """
  @spec recheck(expected) :: [Vws.Codecs.SCPI.command()]
  def recheck({:before, slot, _commanded}),
    do: [{:rout_clos?, slot}, {:rout_clos?, slot}]

  def recheck({:whole, states}), do: [{:rout_clos?, Enum.map(states, &elem(&1, 0))}]
end
