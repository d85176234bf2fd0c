defmodule Vws.DAQ.Readings do
  @moduledoc """
  One poll of DAQ #1: the raw readings of its sensor channels (the seed's array B, §2.3.6) and the
  same readings in engineering units, as `Vws.DAQ.readings/3` builds them.

    * `volts` / `ohms` — channel number ⇒ the reading as the DAQ returned it;
    * `values` — signal name ⇒ `true`/`false` for a microswitch (closed/open), millimetres for a
      potentiometer (`:vise_jaw_mm`, `:gripper_finger_mm`), newtons for a strain gauge
      (`:vise_force_n`), or `:open_circuit` when the channel read the DMM's overload value (a cut
      wire, a dead sensor) — never a number made up from it;
    * `requested_at` / `received_at` — monotonic microseconds when the poll was sent and when its
      answer came back: a reading taken after an actuator moved has `requested_at` later than the
      moment the relay was confirmed;
    * `seq` — the poll's number.

      iex> r = %Vws.DAQ.Readings{values: %{vise_jaw_mm: 50.04, table_park: true}}
      iex> Vws.DAQ.Readings.get(r, :table_park)
      true
      iex> Vws.DAQ.Readings.get(r, :vacuum_on)
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

  @doc "The channel a signal was read on (for messages), or nil."
  @spec channel(t, atom) :: pos_integer | nil
  def channel(%__MODULE__{channels: channels}, signal), do: Map.get(channels, signal)

  @doc "The voltage readings of slot 1 in channel order: the seed's sixteen-element array B."
  @spec array_b(t) :: [float]
  def array_b(%__MODULE__{volts: volts}), do: volts |> Enum.sort() |> Enum.map(&elem(&1, 1))
end
