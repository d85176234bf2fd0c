defmodule Vws.Partitions.FixtureTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.Interlock
  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Test.DAQFloor

  # The jaw potentiometer's noise is ±0.005 V = ±0.1 mm: a closed vise reads 0.0 or 0.1 mm.
  # Fault tests: short enough that a failure is told quickly, long enough that a loaded
  # machine's late polls do not fail the command that works before it.
  @short [
    partitions: [
      fixture: [options: [timeout_ms: 1_500, interlock: [timeout: 1_000, retry_ms: 50]]]
    ]
  ]

  defp number(text, regex) do
    [value] = Regex.run(regex, text, capture: :all_but_first)
    {value, ""} = Float.parse(value)
    value
  end

  test "CLOSE on a part clamps it: DONE, VISE locked with the part in it; OPEN releases it" do
    %{peer: peer, plant: plant} = DAQFloor.start()
    :ok = Plant.set_part(plant, :vise, true)

    assert DAQFloor.await_status(peer, "VISE", &(&1 =~ "PART IN VISE")) =~
             ~r/^VISE JAWS ARE 1(49\.9|50\.0|50\.1) MM APART AND VISE IS UNLOCKED PART IN VISE$/

    assert DAQFloor.command(peer, "F", 1, "CLOSE") == "DONE"
    text = DAQFloor.status(peer, "VISE")
    assert text =~ ~r/^VISE JAWS ARE \d+\.\d MM APART AND VISE IS LOCKED PART IN VISE$/
    assert_in_delta number(text, ~r/JAWS ARE (\S+) MM/), 50.0, 0.2
    assert Plant.snapshot(plant).vise.force_n >= 800

    assert DAQFloor.command(peer, "F", 2, "OPEN") == "DONE"

    assert DAQFloor.status(peer, "VISE") =~
             ~r/^VISE JAWS ARE 1(49\.9|50\.0|50\.1) MM APART AND VISE IS UNLOCKED PART IN VISE$/
  end

  test "CLOSE on an empty vise: the jaws close on their stop, ERROR PART NOT IN VISE at once" do
    # the default timeout: this ends on what is read, not by waiting
    %{peer: peer} = DAQFloor.start()
    t0 = System.monotonic_time(:millisecond)

    assert DAQFloor.command(peer, "F", 1, "CLOSE") =~
             ~r/^ERROR PART NOT IN VISE \(JAWS CLOSED TO 0\.[01] MM\)$/

    assert System.monotonic_time(:millisecond) - t0 < 4_000

    assert DAQFloor.status(peer, "VISE") =~
             ~r/^VISE JAWS ARE 0\.[01] MM APART AND VISE IS UNLOCKED PART NOT IN VISE$/
  end

  test "a weak clamp: ERROR VISE FORCE f N BELOW 800 N with the force as read" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.set_part(plant, :vise, true)
    :ok = Plant.inject_fault(plant, :weak_clamp, where: :vise, force_n: 310)
    answer = DAQFloor.command(peer, "F", 1, "CLOSE")
    assert answer =~ ~r/^ERROR VISE FORCE \d+ N BELOW 800 N$/
    # the gauge's noise is ±0.05 ohm = ±5 N
    assert_in_delta number(answer, ~r/FORCE (\d+) N/), 310, 6
    assert DAQFloor.status(peer, "VISE") =~ "VISE IS UNLOCKED PART IN VISE"
  end

  test "a stuck CLOSE valve: ERROR VISE DID NOT CLOSE with the jaws as read" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.set_part(plant, :vise, true)
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vise_close_valve)
    answer = DAQFloor.command(peer, "F", 1, "CLOSE")
    assert answer =~ ~r/^ERROR VISE DID NOT CLOSE \(JAWS \d+\.\d MM APART\)$/
    assert_in_delta number(answer, ~r/JAWS (\S+) MM/), 150.0, 0.2
  end

  test "a part that is not there (no_part fault): ERROR PART NOT IN VISE" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.set_part(plant, :vise, true)
    :ok = Plant.inject_fault(plant, :no_part, where: :vise)

    assert DAQFloor.command(peer, "F", 1, "CLOSE") =~
             ~r/^ERROR PART NOT IN VISE \(JAWS CLOSED TO 0\.[01] MM\)$/
  end

  test "a broken part-present switch: the force is there but the part is not confirmed" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.set_part(plant, :vise, true)
    :ok = Plant.inject_fault(plant, :broken_switch, switch: :vise_part_present)
    answer = DAQFloor.command(peer, "F", 1, "CLOSE")
    assert answer =~ ~r/^ERROR VISE FORCE \d+ N BUT PART NOT IN VISE$/
    assert_in_delta number(answer, ~r/FORCE (\d+) N/), 2000, 6
  end

  test "an open-circuit force gauge: ERROR naming the channel; VISE status says NO DATA" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.set_part(plant, :vise, true)
    :ok = Plant.inject_fault(plant, :sensor_open_circuit, signal: :vise_force_n)
    assert DAQFloor.command(peer, "F", 1, "CLOSE") == "ERROR VISE SENSOR CH 117 OPEN CIRCUIT"
    assert DAQFloor.status(peer, "VISE") == "NO DATA (VISE SENSOR CH 117 OPEN CIRCUIT)"
  end

  test "a stuck OPEN valve or a broken open switch: ERROR VISE DID NOT OPEN" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.set_part(plant, :vise, true)
    assert DAQFloor.command(peer, "F", 1, "CLOSE") == "DONE"
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vise_open_valve)
    answer = DAQFloor.command(peer, "F", 2, "OPEN")
    assert answer =~ ~r/^ERROR VISE DID NOT OPEN \(JAWS \d+\.\d MM APART, FORCE \d+ N\)$/
    assert_in_delta number(answer, ~r/JAWS (\S+) MM/), 50.0, 0.2

    :ok = Plant.clear_fault(plant, :all)
    :ok = Plant.inject_fault(plant, :broken_switch, switch: :vise_fully_open)
    answer = DAQFloor.command(peer, "F", 3, "OPEN")
    assert answer =~ ~r/^ERROR VISE DID NOT OPEN \(JAWS \d+\.\d MM APART, FORCE \d+ N\)$/
    assert_in_delta number(answer, ~r/JAWS (\S+) MM/), 150.0, 0.2
  end

  test "a DAQ that stops answering: the table's park switch cannot be read, the vise stays" do
    %{peer: peer, daq: daq, plant: plant} =
      DAQFloor.start([vws_status: [timeout_ms: 100]] ++ @short)

    :ok = DAQ.set_fault(daq, :mute)

    # no fresh reading came (the poll timed out), or VWS_STATUS already says so
    assert DAQFloor.command(peer, "F", 1, "CLOSE") =~
             ~r/^ERROR INTERLOCK TABLE (PARK SWITCH NOT READ|NO DATA) \(DAQ #1 NOT ANSWERING\)$/

    assert Plant.snapshot(plant).vise.jaw_mm == 150.0
  end

  test "DISABLE_TABLE and RELEASE_TABLE take and give up the table for the vise" do
    %{peer: peer, ws: ws} =
      DAQFloor.start(partitions: [fixture: [options: [interlock: [timeout: 300, retry_ms: 50]]]])

    assert Interlock.holder(ws, :table) == nil
    assert DAQFloor.command(peer, "F", 1, "DISABLE_TABLE") == "DONE"
    assert [%{holder: :fixture, reasons: [:disabled]}] = Interlock.held(ws)
    # again is fine
    assert DAQFloor.command(peer, "F", 2, "DISABLE_TABLE") == "DONE"
    assert DAQFloor.command(peer, "F", 3, "RELEASE_TABLE") == "DONE"
    assert Interlock.holder(ws, :table) == nil
    assert DAQFloor.command(peer, "F", 4, "RELEASE_TABLE") == "DONE"

    # the robot shares the table with the vise
    :ok = Interlock.acquire(ws, :table, :robot, 0)
    assert DAQFloor.command(peer, "F", 5, "DISABLE_TABLE") == "DONE"
    assert Interlock.holders(ws, :table) == [:robot, :fixture]
    assert DAQFloor.command(peer, "F", 6, "RELEASE_TABLE") == "DONE"
    assert Interlock.holders(ws, :table) == [:robot]
    :ok = Interlock.release(ws, :table, :robot)

    # the machine's cycle does not
    :ok = Interlock.acquire(ws, :table, :monarch, 0)

    assert DAQFloor.command(peer, "F", 7, "DISABLE_TABLE") ==
             "ERROR INTERLOCK TABLE HELD BY MONARCH"

    assert DAQFloor.command(peer, "F", 8, "OPEN") == "ERROR INTERLOCK TABLE HELD BY MONARCH"
    assert DAQFloor.command(peer, "F", 9, "RELEASE_TABLE") == "DONE"
    assert Interlock.holders(ws, :table) == [:monarch]
  end

  test "a vise command that fails keeps the table until the vise is found at rest" do
    %{peer: peer, ws: ws, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vise_close_valve)
    assert DAQFloor.command(peer, "F", 1, "CLOSE") =~ "ERROR VISE DID NOT CLOSE"
    assert [%{holder: :fixture, reasons: [:vise]}] = Interlock.held(ws)
    # both valves were switched off: nothing moves when the valve comes free
    :ok = Plant.clear_fault(plant, :all)
    refute Plant.snapshot(plant).vise.moving

    assert {:error, "INTERLOCK TABLE HELD BY FIXTURE"} =
             Interlock.acquire(ws, :table, :monarch, 0)

    assert DAQFloor.command(peer, "F", 2, "RELEASE_TABLE") == "DONE"
    assert Interlock.held(ws) == []
  end

  test "RELEASE_TABLE with the vise unreadable after a failure keeps the table" do
    %{peer: peer, ws: ws, daq: daq, plant: plant} =
      DAQFloor.start([vws_status: [timeout_ms: 100]] ++ @short)

    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vise_close_valve)
    assert DAQFloor.command(peer, "F", 1, "CLOSE") =~ "ERROR VISE DID NOT CLOSE"
    :ok = DAQ.set_fault(daq, :mute)
    assert DAQFloor.command(peer, "F", 2, "RELEASE_TABLE") =~ "ERROR VISE NOT AT REST"
    assert Interlock.holders(ws, :table) == [:fixture]
  end
end
