defmodule Vws.Partitions.GripperTest do
  use ExUnit.Case, async: true

  alias Vws.Sim.Plant
  alias Vws.Test.DAQFloor

  # Fault tests give the sensors 1.5 s to confirm (the plant runs 1000x: a stroke takes 0.5 ms):
  # short enough that a failure is told quickly, long enough that a loaded machine's late polls
  # do not fail the command that works before it (CLOSE, then a faulty OPEN). Success paths keep
  # the default timeouts.
  @short [partitions: [gripper: [options: [timeout_ms: 1_500]]]]

  defp mm_apart(text) do
    [mm] = Regex.run(~r/FINGERS (?:ARE )?(\d+\.\d) MM APART/, text, capture: :all_but_first)
    String.to_float(mm)
  end

  test "CLOSE on nothing closes the fingers on themselves: DONE, and the status shows it" do
    %{peer: peer, plant: plant} = DAQFloor.start()
    assert DAQFloor.status(peer, "GRIPPER") == "GRIPPER IS OPEN AND INDEXER ROTATED 0 DEG"
    assert DAQFloor.command(peer, "G", 1, "CLOSE") == "DONE"

    assert DAQFloor.status(peer, "GRIPPER") ==
             "FINGERS ARE 0.0 MM APART AND INDEXER ROTATED 0 DEG"

    assert Plant.snapshot(plant).gripper.finger_mm == 0.0
  end

  test "CLOSE on a part stops against it; OPEN puts it down and opens fully" do
    %{peer: peer, plant: plant} = DAQFloor.start()
    :ok = Plant.set_part(plant, :tray1, true)
    :ok = Plant.set_robot(plant, %{volume: :tray1})
    assert DAQFloor.command(peer, "G", 1, "CLOSE") == "DONE"
    text = DAQFloor.status(peer, "GRIPPER")
    assert text =~ ~r/^FINGERS ARE \d+\.\d MM APART AND INDEXER ROTATED 0 DEG$/
    assert_in_delta mm_apart(text), 50.0, 0.2
    assert Plant.snapshot(plant).gripper.holding

    assert DAQFloor.command(peer, "G", 2, "OPEN") == "DONE"
    assert DAQFloor.status(peer, "GRIPPER") == "GRIPPER IS OPEN AND INDEXER ROTATED 0 DEG"
    refute Plant.snapshot(plant).gripper.holding
  end

  test "ROTATE_n turns the indexer to each position" do
    %{peer: peer, plant: plant} = DAQFloor.start()

    for {deg, n} <- Enum.with_index([90, 270, 180, 0], 1) do
      assert DAQFloor.command(peer, "G", n, "ROTATE_#{deg}") == "DONE"
      assert DAQFloor.status(peer, "GRIPPER") == "GRIPPER IS OPEN AND INDEXER ROTATED #{deg} DEG"
      assert_in_delta Plant.snapshot(plant).gripper.indexer_deg, deg, 1.0
    end
  end

  test "a stuck CLOSE solenoid: ERROR GRIPPER DID NOT CLOSE with the fingers as read" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :gripper_close_solenoid)
    answer = DAQFloor.command(peer, "G", 1, "CLOSE")
    assert answer =~ ~r/^ERROR GRIPPER DID NOT CLOSE \(FINGERS \d+\.\d MM APART\)$/
    assert_in_delta mm_apart(answer), 80.0, 0.2
  end

  test "a stuck OPEN solenoid: ERROR GRIPPER DID NOT OPEN" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    assert DAQFloor.command(peer, "G", 1, "CLOSE") == "DONE"
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :gripper_open_solenoid)

    assert DAQFloor.command(peer, "G", 2, "OPEN") ==
             "ERROR GRIPPER DID NOT OPEN (FINGERS 0.0 MM APART)"
  end

  test "a broken fully-open switch: OPEN is not confirmed, whatever the potentiometer says" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    assert DAQFloor.command(peer, "G", 1, "CLOSE") == "DONE"
    :ok = Plant.inject_fault(plant, :broken_switch, switch: :gripper_fully_open)
    answer = DAQFloor.command(peer, "G", 2, "OPEN")
    assert answer =~ ~r/^ERROR GRIPPER DID NOT OPEN \(FINGERS \d+\.\d MM APART\)$/
    assert_in_delta mm_apart(answer), 80.0, 0.2
    assert DAQFloor.status(peer, "GRIPPER") =~ ~r/^FINGERS ARE \d+\.\d MM APART AND INDEXER/
  end

  test "a stuck indexer bit: ERROR INDEXER DID NOT REACH with where it is" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :indexer_bit0)

    assert DAQFloor.command(peer, "G", 1, "ROTATE_90") ==
             "ERROR INDEXER DID NOT REACH 90 DEG (AT 0 DEG)"

    # ROTATE_270 needs bit 0 too: it stops at 180
    assert DAQFloor.command(peer, "G", 2, "ROTATE_270") ==
             "ERROR INDEXER DID NOT REACH 270 DEG (AT 180 DEG)"
  end

  test "a broken position switch: the indexer is between positions as far as the CEC knows" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :broken_switch, switch: :indexer_90)

    assert DAQFloor.command(peer, "G", 1, "ROTATE_90") ==
             "ERROR INDEXER DID NOT REACH 90 DEG (BETWEEN POSITIONS)"

    assert DAQFloor.status(peer, "GRIPPER") == "GRIPPER IS OPEN AND INDEXER BETWEEN POSITIONS"
  end

  test "a part that is not there (no_part): CLOSE ends as the seed says, fingers on themselves" do
    %{peer: peer, plant: plant} = DAQFloor.start()
    :ok = Plant.set_part(plant, :tray1, true)
    :ok = Plant.set_robot(plant, %{volume: :tray1})
    :ok = Plant.inject_fault(plant, :no_part, where: :gripper)
    assert DAQFloor.command(peer, "G", 1, "CLOSE") == "DONE"

    assert DAQFloor.status(peer, "GRIPPER") ==
             "FINGERS ARE 0.0 MM APART AND INDEXER ROTATED 0 DEG"
  end

  test "an open-circuit finger potentiometer: ERROR naming the channel; the status says NO DATA" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :sensor_open_circuit, channel: 108)
    assert DAQFloor.command(peer, "G", 1, "CLOSE") == "ERROR GRIPPER SENSOR CH 108 OPEN CIRCUIT"
    assert DAQFloor.status(peer, "GRIPPER") == "NO DATA (GRIPPER SENSOR CH 108 OPEN CIRCUIT)"
  end
end
