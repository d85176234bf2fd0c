defmodule Vws.Ops.Web.StateTest do
  # The dashboard's data, piece by piece, from the shapes the links and mailboxes really have.
  use ExUnit.Case, async: true

  alias Vws.Links.DAQ.Readings
  alias Vws.Ops.Web.State

  test "sensors: DAQ #1's quantities with units, the pallet clamp forces, switches in words" do
    readings = %Readings{
      seq: 12,
      values: %{
        vise_jaw_mm: 49.96,
        gripper_finger_mm: :open_circuit,
        vise_force_n: 1998.7,
        table_park: true,
        vacuum_on: false
      }
    }

    devices = [%{location: 11, name: "SENSORS", value: readings, age_ms: 7}]
    pallet = {%{clamped: true, x: true, y: false, force1_n: 5000.04, force2_n: 9.9e37}, 300}

    s = State.sensors(devices, %{pallet: pallet})
    assert %{poll: 12, age_ms: 7, note: nil, pallet_age_ms: 300} = s

    by_key = Map.new(s.quantities, &{&1.key, &1})

    # shown as the CEC judges them (mm with one decimal, N whole), the raw value beside
    assert %{name: "vise jaw width", value: 50.0, raw: 49.96, unit: "mm", source: "DAQ #1"} =
             by_key["daq1.vise_jaw_mm"]

    assert %{name: "vise clamp force", value: 1999, raw: 1998.7, unit: "N"} =
             by_key["daq1.vise_force_n"]

    # a cut wire is no number, and says so
    assert %{value: nil, note: "open circuit"} = by_key["daq1.gripper_finger_mm"]

    assert %{name: "pallet clamp force 1", value: 5000, raw: 5000.0, unit: "N"} =
             by_key["pallet.force1_n"]

    assert %{value: nil, note: "overload"} = by_key["pallet.force2_n"]

    assert %{name: "table park", state: "closed"} in s.switches
    assert %{name: "vacuum on", state: "open"} in s.switches
    assert %{name: "pallet y", state: "no"} in s.switches

    # no poll yet: the reason in words, no numbers made up
    s =
      State.sensors(
        [%{location: 11, name: "SENSORS", value: {:no_data, "DAQ #1 NOT CONNECTED"}, age_ms: 5}],
        %{}
      )

    assert %{poll: nil, note: "NO DATA (DAQ #1 NOT CONNECTED)", quantities: [], switches: []} = s
  end

  test "a link row: state, counters, retries, last error, details in words" do
    row = %{
      id: {Vws.Links.HPIB, "VWS", 9},
      name: "DAQ #1 (HPIB 9)",
      pid: self(),
      module: Vws.Links.HPIB,
      state: :connecting,
      info: %{
        state: :connecting,
        device: "DAQ #1",
        address: 9,
        endpoint: "tcp://127.0.0.1:5025",
        connects: 3,
        timeouts: 2,
        retried: 4,
        requests: 100,
        queued: 0,
        unsolicited: 0,
        last_error: :econnrefused
      }
    }

    l = State.link(row)

    assert %{
             id: "DAQ #1 (HPIB 9)",
             state: "connecting",
             state_class: "bad",
             retries: 4,
             last_error: "econnrefused",
             details: "endpoint tcp://127.0.0.1:5025"
           } = l

    assert %{key: "timeouts", value: 2} in l.counters

    # a VAL II: its DDCMP line's retransmissions count as retries, its error shows
    val = %{
      id: :val,
      name: "VAL II (DDCMP)",
      pid: self(),
      module: Vws.Links.VAL,
      state: {:ready, :still},
      info: %{
        state: {:ready, :still},
        link: self(),
        counts: %{in: 2, out: 1},
        short_status: "MONITOR SPEED 50.0 STOPPED",
        line: %{counters: %{retransmitted: 3, timeouts: 1}, last_error: {:timeout, 3}, a: 5}
      }
    }

    l = State.link(val)
    assert %{state: "ready still", state_class: "ok", retries: 3, last_error: "timeout 3"} = l
    assert l.details == "short status MONITOR SPEED 50.0 STOPPED"
    refute Enum.any?(l.counters, &(&1.key == "line a"))

    # a row that could not be read says why
    l =
      State.link(%{
        id: :x,
        name: "x",
        pid: nil,
        module: nil,
        state: :unreadable,
        info: %{error: "** (FunctionClauseError) no function clause matching"}
      })

    assert %{state: "unreadable", state_class: "bad", last_error: "** (FunctionClauseError)" <> _} =
             l
  end

  test "an NC transfer's progress: so far, in all, rate and ETA" do
    t = %{
      lines: 40,
      bytes: 1000,
      total_lines: 100,
      total_bytes: 2500,
      started_ms: 10_000
    }

    p = State.progress("WC", "UPLOAD_SUN", 12, :lines, t, 12_000)

    assert %{
             link: "WC",
             kind: "UPLOAD_SUN",
             number: "0012",
             unit: "lines",
             done: 40,
             total: 100,
             percent: 40,
             bytes_per_s: 500,
             eta_s: 3.0
           } = p

    # a download's length is not announced: no percentage, no ETA, a rate all the same
    p =
      State.progress(
        "WC",
        "DOWNLOAD_HP",
        3,
        :lines,
        %{t | total_lines: nil, total_bytes: nil},
        11_000
      )

    assert %{total: nil, percent: nil, eta_s: nil, bytes_per_s: 1000} = p
  end

  test "the whole state is JSON of words and numbers, without workstations as well" do
    json = IO.iodata_to_binary(Vws.Ops.Web.JSON.encode(State.build()))
    assert json =~ ~s("workstations":)
    refute json =~ "#PID"
  end

  test "deadband: noise around zero within the partitions' bands is zero, never negative" do
    assert State.deadband(-0.1, "mm") === 0.0
    assert State.deadband(0.5, "mm") === 0.0
    assert State.deadband(-0.5, "mm") === 0.0
    assert State.deadband(0.6, "mm") === 0.6
    assert State.deadband(-25.0, "N") === 0
    assert State.deadband(24.9, "N") === 0
    assert State.deadband(26.2, "N") === 26
    assert State.deadband(1.234, "V") === 1.23
    # the same bands the fixture partition judges rest by
    assert %{mm: 0.5, n: 25.0} = Vws.Partitions.Fixture.noise_bands()
  end

  test "severity: not read yet is neutral, errors are errors" do
    assert State.severity("NO DATA (GE-2000 NOT READ YET)") == "neutral"
    assert State.severity("NO DATA (DAQ #1 NOT READ YET)") == "neutral"
    assert State.severity("NO DATA (VAL II NOT READ YET)") == "neutral"
    assert State.severity("NONE") == "neutral"
    assert State.severity(nil) == "neutral"
    assert State.severity("ERROR NO LINK TO DAQ #1") == "error"
    assert State.severity("NO DATA (NO LINK TO DAQ #1)") == "error"
    assert State.severity("DONE") == "ok"
    assert State.severity("EXECUTING") == "ok"
    assert State.severity("JAWS OPEN 50.0 MM") == "ok"
  end
end
