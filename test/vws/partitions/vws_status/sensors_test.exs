defmodule Vws.Partitions.VwsStatus.SensorsTest do
  use ExUnit.Case, async: true

  alias Vws.Links.DAQ.Readings
  alias Vws.Links.HPIB
  alias Vws.Partitions.VwsStatus.Sensors

  doctest Sensors

  test "without a fresh reading every location it keeps says why, location 11 as data" do
    assert Sensors.no_data("DAQ #1 NOT ANSWERING") ==
             for(loc <- [1, 2, 3, 4, 5, 7], do: {loc, "NO DATA (DAQ #1 NOT ANSWERING)"}) ++
               [{11, {:no_data, "DAQ #1 NOT ANSWERING"}}]

    assert Enum.sort(Sensors.locations()) == [1, 2, 3, 4, 5, 7, 11]
  end

  test "the other devices' locations: not read yet when their link is configured, else no link" do
    assert Sensors.other_locations([:robot]) == [
             {6, "NO DATA (NO LINK TO GE-2000)"},
             {8, "NO DATA (NO LINK TO GE-2000)"},
             {9, "NO DATA (VAL II NOT READ YET)"},
             {10, "NO DATA (NO LINK TO HYDRAULIC CONTROLLER)"}
           ]
  end

  test "a tray lock: its relay and the check of its lock-pin switch" do
    {{:tray2_lock, :close}, check} = Sensors.tray_lock(2, :lock)
    assert check.(%Readings{values: %{tray2_locked: true}}) == :ok

    assert check.(%Readings{values: %{tray2_locked: false}}) ==
             {:wait, "TRAY 2 LOCK PIN NOT ENGAGED"}

    {{:tray1_lock, :open}, check} = Sensors.tray_lock(1, :unlock)
    assert check.(%Readings{values: %{tray1_locked: false}}) == :ok

    assert check.(%Readings{values: %{tray1_locked: true}}) ==
             {:wait, "TRAY 1 LOCK PIN NOT RELEASED"}

    assert check.(%Readings{values: %{tray1_locked: :open_circuit}}) ==
             {:wait, "TRAY 1 LOCK SWITCH OPEN CIRCUIT"}
  end

  test "why readings are stale, from the last poll's error" do
    assert Sensors.stale_reason(nil, true, nil) == "DAQ #1 NOT ANSWERING"

    assert Sensors.stale_reason(%HPIB.Error{reason: :timeout}, false, nil) ==
             "DAQ #1 NOT ANSWERING"

    assert Sensors.stale_reason(%HPIB.Error{reason: :bad_response}, false, nil) ==
             "DAQ #1 BAD ANSWER"

    assert Sensors.stale_reason(%HPIB.Error{reason: :not_connected}, false, nil) ==
             "DAQ #1 NOT CONNECTED"

    assert Sensors.stale_reason(nil, false, "DAQ #1 NOT READ YET") == "DAQ #1 NOT READ YET"
  end

  test "the values of signals, in the order asked" do
    r = %Readings{values: %{vise_jaw_mm: 12.5, vise_force_n: 900.0}}
    assert Sensors.values(r, [:vise_force_n, :vise_jaw_mm], "VISE") == {:ok, [900.0, 12.5]}
  end
end
