defmodule Vws.Links.DAQ.ChannelMap do
  @moduledoc """
  The plant's channel map and constants: `priv/plant.exs`, loaded and checked.

  The wiring of the DAQs is the product's configuration: the CEC's driver (`Vws.Links.DAQ`) and the
  hydraulic controller read it from here, and the plant simulator (`Vws.Sim.Plant`) is wired by
  the same file — the simulator reads the product's map, never the other way round.

  The file is one Elixir map (see its comments): `:daq1` and `:daq2` map channel numbers to
  `%{kind: :switch | :pot | :gauge | :spare | :actuator, signal: name, ...}`; `:switch`, `:noise`,
  `:overload`, `:motion`, `:part_width_mm` and `:table_volumes` hold the constants. `load/1`
  turns it into a `t:t/0` with the channels keyed `{daq, channel}` and an index from signal name
  to channel, so drivers can say `channel(config, :vise_force_n)` instead of `117`.

      iex> config = Vws.Links.DAQ.ChannelMap.load()
      iex> Vws.Links.DAQ.ChannelMap.channel(config, :vise_force_n)
      {:daq1, 117}
      iex> Vws.Links.DAQ.ChannelMap.channel(config, :swing_clamp1_valve)
      {:daq2, 203}
  """

  @type daq :: :daq1 | :daq2
  @type address :: {daq, pos_integer}
  @type kind :: :switch | :pot | :gauge | :spare | :actuator

  @type t :: %{
          channels: %{address => map},
          signals: %{atom => address},
          switch: map,
          noise: map,
          overload: float,
          motion: map,
          part_width_mm: float,
          table_volumes: [atom]
        }

  @daqs [:daq1, :daq2]

  @sensors %{
    switch: ~w(vise_part_present vise_fully_open table_park tray1_in tray2_in gripper_fully_open
               indexer_0 indexer_90 indexer_180 indexer_270 vacuum_on tray1_locked tray2_locked
               pallet_x pallet_y changer1_released)a,
    pot: ~w(vise_jaw_mm gripper_finger_mm)a,
    gauge: ~w(vise_force_n clamp1_force_n clamp2_force_n)a,
    spare: [:spare]
  }

  @actuators ~w(gripper_open_solenoid gripper_close_solenoid indexer_bit0 indexer_bit1
                vise_open_valve vise_close_valve vacuum_motor tray1_lock tray2_lock
                cycle_start_relay ram_x_valve ram_y_valve swing_clamp1_valve swing_clamp2_valve)a

  @required_keys %{
    pot: [:volts_at_zero, :volts_per_unit],
    gauge: [:ohms_at_zero, :ohms_per_newton]
  }

  @doc "The path of the shipped channel map, `priv/plant.exs`."
  @spec default_path() :: Path.t()
  def default_path, do: Path.join(:code.priv_dir(:vws), "plant.exs")

  @doc "Every signal name a channel may carry, by kind."
  @spec signals() :: %{kind => [atom]}
  def signals, do: Map.put(@sensors, :actuator, @actuators)

  @doc """
  Loads and checks a channel map. `source` is a file path, or a map in the file's shape that is
  merged (deeply) over the shipped file — `%{motion: %{vise_stroke_s: 3.0}}` changes one time.
  Raises `ArgumentError` naming the entry when the map is wrong: an unknown kind or signal, a
  signal on two channels, a missing conversion constant.
  """
  @spec load(Path.t() | map) :: t
  def load(source \\ default_path())

  def load(path) when is_binary(path) do
    {raw, _binding} = Code.eval_file(path)
    normalize(raw)
  end

  def load(overrides) when is_map(overrides) do
    {raw, _binding} = Code.eval_file(default_path())
    normalize(deep_merge(raw, overrides))
  end

  @doc "The `{daq, channel}` carrying `signal`, or nil when it is not wired."
  @spec channel(t, atom) :: address | nil
  def channel(%{signals: signals}, signal), do: Map.get(signals, signal)

  @doc "The entry of channel `address`, or nil."
  @spec entry(t, address) :: map | nil
  def entry(%{channels: channels}, address), do: Map.get(channels, address)

  defp normalize(raw) when is_map(raw) do
    channels =
      for daq <- @daqs, {number, entry} <- Map.get(raw, daq, %{}), into: %{} do
        {{daq, number}, check_entry(daq, number, entry)}
      end

    signals =
      Enum.reduce(channels, %{}, fn {address, %{signal: signal}}, acc ->
        if Map.has_key?(acc, signal) and signal != :spare do
          raise ArgumentError, "plant config: signal #{inspect(signal)} is on two channels"
        end

        Map.put(acc, signal, address)
      end)

    %{
      channels: channels,
      signals: signals,
      switch: fetch!(raw, :switch),
      noise: fetch!(raw, :noise),
      overload: fetch!(raw, :overload) * 1.0,
      motion: fetch!(raw, :motion),
      part_width_mm: fetch!(raw, :part_width_mm) * 1.0,
      table_volumes: fetch!(raw, :table_volumes)
    }
  end

  defp normalize(other),
    do: raise(ArgumentError, "plant config must be a map, got #{inspect(other)}")

  defp check_entry(daq, number, %{kind: kind, signal: signal} = entry)
       when is_integer(number) do
    known = Map.get(signals(), kind) || bad(daq, number, "unknown kind #{inspect(kind)}")

    unless signal in known do
      bad(daq, number, "#{inspect(signal)} is not a #{inspect(kind)} signal")
    end

    for key <- Map.get(@required_keys, kind, []), not is_number(Map.get(entry, key)) do
      bad(daq, number, "#{inspect(kind)} needs a number #{inspect(key)}")
    end

    entry
  end

  defp check_entry(daq, number, _entry), do: bad(daq, number, "needs :kind and :signal")

  defp bad(daq, number, text),
    do: raise(ArgumentError, "plant config #{daq} channel #{inspect(number)}: #{text}")

  defp fetch!(raw, key) do
    case Map.fetch(raw, key) do
      {:ok, value} -> value
      :error -> raise ArgumentError, "plant config: missing #{inspect(key)}"
    end
  end

  defp deep_merge(left, right) do
    Map.merge(left, right, fn
      _key, %{} = l, %{} = r -> deep_merge(l, r)
      _key, _l, r -> r
    end)
  end
end
