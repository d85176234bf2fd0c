defmodule Vws.Partitions.VacuumTest do
  use ExUnit.Case, async: true

  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Test.DAQFloor
  import Vws.Test.Eventually

  # Fault tests: short enough that a failure is told quickly, long enough that a loaded
  # machine's late polls do not fail the command that works before it.
  @short [partitions: [vacuum: [options: [timeout_ms: 1_500]]]]

  test "ON and OFF, confirmed by the pressure switch; the VACUUM status follows" do
    %{peer: peer, plant: plant} = DAQFloor.start()
    assert DAQFloor.status(peer, "VACUUM") == "VACUUM IS OFF"
    assert DAQFloor.command(peer, "V", 1, "ON") == "DONE"
    assert DAQFloor.status(peer, "VACUUM") == "VACUUM IS ON"
    assert Plant.snapshot(plant).vacuum.on
    assert DAQFloor.command(peer, "V", 2, "OFF") == "DONE"
    assert DAQFloor.status(peer, "VACUUM") == "VACUUM IS OFF"
  end

  test "a stuck motor contactor: ERROR VACUUM DID NOT TURN ON" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vacuum_motor)

    assert DAQFloor.command(peer, "V", 1, "ON") ==
             "ERROR VACUUM DID NOT TURN ON (PRESSURE SWITCH OPEN)"
  end

  test "a motor that will not stop: ERROR VACUUM DID NOT TURN OFF" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    assert DAQFloor.command(peer, "V", 1, "ON") == "DONE"
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vacuum_motor)

    assert DAQFloor.command(peer, "V", 2, "OFF") ==
             "ERROR VACUUM DID NOT TURN OFF (PRESSURE SWITCH CLOSED)"
  end

  test "a broken pressure switch: ON is not confirmed" do
    %{peer: peer, plant: plant} = DAQFloor.start(@short)
    :ok = Plant.inject_fault(plant, :broken_switch, switch: :vacuum_on)

    assert DAQFloor.command(peer, "V", 1, "ON") ==
             "ERROR VACUUM DID NOT TURN ON (PRESSURE SWITCH OPEN)"
  end

  test "a DAQ that is gone: ERROR DAQ #1 NOT CONNECTED" do
    %{peer: peer, daq: daq, ws: ws} = DAQFloor.start(@short)
    GenServer.stop(daq)
    assert eventually(fn -> Vws.Links.HPIB.info({ws, 9}).state == :disconnected end)
    assert DAQFloor.command(peer, "V", 1, "ON") == "ERROR DAQ #1 NOT CONNECTED"
  end

  test "a DAQ that answers too late: ERROR with the timeout" do
    %{peer: peer, daq: daq} = DAQFloor.start([vws_status: [timeout_ms: 50]] ++ @short)
    :ok = DAQ.set_fault(daq, {:delay_ms, 200})

    # the poll ahead of it timed out first (the connection is being made again), or it did
    assert DAQFloor.command(peer, "V", 1, "ON") =~
             ~r/^ERROR DAQ #1 NOT ANSWERING \((NO ANSWER IN 50 MS|TIMED OUT, RECONNECTING)\)$/
  end
end
