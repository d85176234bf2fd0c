defmodule Vws.Partitions.FixtureTest do
  use ExUnit.Case, async: true

  alias Vws.Partitions.Fixture
  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Test.DAQFloor

  # The jaw potentiometer's noise is ±0.005 V = ±0.1 mm: a closed vise reads 0.0 or 0.1 mm.
  @short [partitions: [fixture: [options: [timeout_ms: 300]]]]

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

  test "a DAQ that stops answering: ERROR with the timeout" do
    %{peer: peer, daq: daq} = DAQFloor.start([vws_status: [timeout_ms: 100]] ++ @short)
    :ok = DAQ.set_fault(daq, :mute)

    # the poll ahead of it timed out first (the connection is being made again), or it did
    assert DAQFloor.command(peer, "F", 1, "CLOSE") =~
             ~r/^ERROR DAQ #1 NOT ANSWERING \((NO ANSWER IN 100 MS|TIMED OUT, RECONNECTING)\)$/
  end

  test "DISABLE_TABLE and RELEASE_TABLE set and clear the table interlock flag" do
    %{peer: peer, ws: ws} = DAQFloor.start()
    assert Fixture.table_interlock_holder(ws) == nil
    assert DAQFloor.command(peer, "F", 1, "DISABLE_TABLE") == "DONE"
    assert Fixture.table_interlock_holder(ws) == :fixture
    # again by the same holder is fine
    assert DAQFloor.command(peer, "F", 2, "DISABLE_TABLE") == "DONE"
    assert DAQFloor.command(peer, "F", 3, "RELEASE_TABLE") == "DONE"
    assert Fixture.table_interlock_holder(ws) == nil
    assert DAQFloor.command(peer, "F", 4, "RELEASE_TABLE") == "DONE"

    # another holder has it
    assert Fixture.table_interlock(ws, :robot, :disable) == :ok

    assert DAQFloor.command(peer, "F", 5, "DISABLE_TABLE") ==
             "ERROR TABLE HELD BY ROBOT"

    assert DAQFloor.command(peer, "F", 6, "RELEASE_TABLE") ==
             "ERROR TABLE HELD BY ROBOT"

    assert Fixture.table_interlock_holder(ws) == :robot
  end
end
