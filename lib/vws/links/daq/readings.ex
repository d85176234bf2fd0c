defmodule Vws.Links.DAQ.Readings do
  @moduledoc """
  One poll of DAQ #1: the raw readings of its sensor channels (the seed's array B, §2.3.6) and the
  same readings in engineering units, as `Vws.Links.DAQ.readings/3` builds them.

    * `volts` / `ohms` — channel number ⇒ the reading as the DAQ returned it;
    * `values` — signal name ⇒ `true`/`false` for a microswitch (closed/open), millimetres for a
      potentiometer (`:vise_jaw_mm`, `:gripper_finger_mm`), newtons for a strain gauge
      (`:vise_force_n`), or `:open_circuit` when the channel read the DMM's overload value (a cut
      wire, a dead sensor) — never a number made up from it;
    * `requested_at` / `received_at` — monotonic microseconds when the poll was sent and when its
      answer came back: a reading taken after an actuator moved has `requested_at` later than the
      moment the relay was confirmed;
    * `seq` — the poll's number.

      iex> r = %Vws.Links.DAQ.Readings{values: %{vise_jaw_mm: 50.04, table_park: true}}
      iex> Vws.Links.DAQ.Readings.get(r, :table_park)
      true
      iex> Vws.Links.DAQ.Readings.get(r, :vacuum_on)
      nil
  """

  @type value :: boolean | float | :open_circuit
  @type t :: %__MODULE__{
          seq: non_neg_integer,
          requested_at: integer,
          received_at: integer,
          volts: %{pos_integer => float},
          ohms: %{pos_integer => float},
          values: %{atom => value},
          channels: %{atom => pos_integer}
        }

  defstruct seq: 0,
            requested_at: 0,
            received_at: 0,
            volts: %{},
            ohms: %{},
            values: %{},
            channels: %{}

  @doc "The value of a signal: a switch state, millimetres, newtons, `:open_circuit`; nil if not read."
  @spec get(t, atom) :: value | nil
  def get(%__MODULE__{values: values}, signal), do: Map.get(values, signal)

  @doc """
  The values of `signals` in this reading, in order: `{:ok, values}`, or why one cannot be had —
  the first signal that reads the DMM's overload value (`{:open_circuit, channel}`) or is not
  wired (`{:not_wired, signal}`). The device texts (`Vws.Links.DAQ.DeviceStatus`) and the
  partitions' checks (`Vws.Partitions.VwsStatus.Sensors.values/3`) both read signals this way.

      iex> r = %Vws.Links.DAQ.Readings{values: %{a: true, b: :open_circuit}, channels: %{b: 104}}
      iex> Vws.Links.DAQ.Readings.fetch(r, [:a])
      {:ok, [true]}
      iex> Vws.Links.DAQ.Readings.fetch(r, [:a, :b, :c])
      {:open_circuit, 104}
      iex> Vws.Links.DAQ.Readings.fetch(r, [:c, :b])
      {:not_wired, :c}
  """
  @spec fetch(t, [atom]) ::
          {:ok, [value]} | {:open_circuit, pos_integer | nil} | {:not_wired, atom}
  def fetch(%__MODULE__{values: values} = r, signals), do: fetch(values, r, signals, [])

  # (a walk of its own, not Enum.reduce_while/3: VWS_STATUS builds six texts from every poll)
  defp fetch(values, r, [signal | rest], acc) do
    case values do
      %{^signal => :open_circuit} -> {:open_circuit, channel(r, signal)}
      %{^signal => nil} -> {:not_wired, signal}
      %{^signal => value} -> fetch(values, r, rest, [value | acc])
      _ -> {:not_wired, signal}
    end
  end

  defp fetch(_values, _r, [], acc), do: {:ok, :lists.reverse(acc)}

  @doc "The channel a signal was read on (for messages), or nil."
  @spec channel(t, atom) :: pos_integer | nil
  def channel(%__MODULE__{channels: channels}, signal), do: Map.get(channels, signal)

  @doc "The voltage readings of slot 1 in channel order: the seed's sixteen-element array B."
  @spec array_b(t) :: [float]
  def array_b(%__MODULE__{volts: volts}), do: volts |> Enum.sort() |> Enum.map(&elem(&1, 1))

  @doc """
  The measured quantities of a poll, for people: `[%{signal, name, value, unit}]` for every
  potentiometer (`"mm"`) and strain gauge (`"N"`) signal, sorted by name; `value` is the number,
  or nil when the channel read open circuit (`open_circuit: true` then).

      iex> r = %Vws.Links.DAQ.Readings{values: %{vise_jaw_mm: 50.04, vise_force_n: :open_circuit, table_park: true}}
      iex> Vws.Links.DAQ.Readings.quantities(r)
      [%{signal: :vise_force_n, name: "vise clamp force", value: nil, unit: "N", open_circuit: true},
       %{signal: :vise_jaw_mm, name: "vise jaw width", value: 50.04, unit: "mm", open_circuit: false}]
  """
  @spec quantities(t) :: [map]
  def quantities(%__MODULE__{values: values}) do
    for {signal, value} <- values, unit = unit(signal), value != true and value != false do
      %{
        signal: signal,
        name: name(signal),
        value: if(is_number(value), do: value),
        unit: unit,
        open_circuit: value == :open_circuit
      }
    end
    |> Enum.sort_by(& &1.name)
  end

  @doc """
  The switches of a poll, for people: `[{name, "closed" | "open" | "open circuit"}]`, by name.

      iex> Vws.Links.DAQ.Readings.switches(%Vws.Links.DAQ.Readings{values: %{tray1_in: true, vacuum_on: false}})
      [{"tray1 in", "closed"}, {"vacuum on", "open"}]
  """
  @spec switches(t) :: [{String.t(), String.t()}]
  def switches(%__MODULE__{values: values}) do
    for {signal, value} <- values, unit(signal) == nil do
      {humanize(to_string(signal)),
       case value do
         true -> "closed"
         false -> "open"
         :open_circuit -> "open circuit"
         other -> to_string(other)
       end}
    end
    |> Enum.sort()
  end

  @doc """
  A poll in one line of words: its number and every quantity with its unit.

      iex> Vws.Links.DAQ.Readings.describe(%Vws.Links.DAQ.Readings{seq: 7, values: %{vise_jaw_mm: 50.04, vise_force_n: 1998.7}})
      "POLL 7: VISE CLAMP FORCE 1999 N, VISE JAW WIDTH 50.0 MM"
  """
  @spec describe(t) :: String.t()
  def describe(%__MODULE__{seq: seq} = r) do
    quantities =
      Enum.map_join(quantities(r), ", ", fn q ->
        String.upcase(q.name) <> " " <> number_text(q)
      end)

    "POLL #{seq}: " <> if(quantities == "", do: "NO QUANTITIES", else: quantities)
  end

  defp number_text(%{open_circuit: true}), do: "OPEN CIRCUIT"
  defp number_text(%{unit: "N", value: v}), do: "#{round(v)} N"

  defp number_text(%{unit: "mm", value: v}),
    do: "#{:erlang.float_to_binary(v / 1, decimals: 1)} MM"

  defp unit(signal) do
    case signal |> to_string() |> String.split("_") |> List.last() do
      "mm" -> "mm"
      "n" -> "N"
      _ -> nil
    end
  end

  defp humanize(text), do: String.replace(text, "_", " ")

  # what the shipped channel map's sensors measure; any other signal by its own name
  defp name(:vise_jaw_mm), do: "vise jaw width"
  defp name(:gripper_finger_mm), do: "gripper finger gap"
  defp name(:vise_force_n), do: "vise clamp force"

  defp name(signal),
    do: signal |> to_string() |> String.replace(~r/_(mm|n)$/, "") |> humanize()
end
