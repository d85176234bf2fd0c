defmodule Vws.CEC.Interlock.RulesTest do
  @moduledoc false
  # The six interlocks of seed §2.3.8, each both ways — allowed when it should be, refused when
  # not — on the whole simulated floor (plant, DAQ #1, GE-2000, VAL II, MHS), with the plant's
  # collision oracle watching: it never records anything.
  use ExUnit.Case, async: true

  alias Vws.CEC.{Interlock, Mailbox}
  alias Vws.Sim.{DAQ, GE2000, MHS, Plant, VAL2}
  alias Vws.Test.SafetyFloor

  setup context do
    f = SafetyFloor.start(Map.get(context, :floor, []))
    on_exit(fn -> SafetyFloor.stop(f) end)
    %{f: f}
  end

  defp run(f, partition, text), do: SafetyFloor.command(f, partition, text)

  defp no_collisions(f), do: assert(SafetyFloor.collisions(f) == [])

  defp robot_at(f), do: VAL2.info(f.robot).location

  # a machining cycle that runs while the test looks
  defp start_cycle(f) do
    assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
    assert run(f, :monarch, "CYCLE_START") == :done
    assert Plant.snapshot(f.plant).table.cycle
  end

  defp end_cycle(f) do
    GE2000.end_cycle(f.ge2000)

    assert SafetyFloor.wait_until(
             fn -> run(f, :monarch, "RELEASE_TABLE") == :done end,
             5_000
           )
  end

  describe "1a: the robot approaches the table only with the machine idle and the table parked" do
    test "allowed: machine idle, table parked", %{f: f} do
      assert run(f, :robot, "DO APPRO VISE/50") == :done
      assert Plant.snapshot(f.plant).robot.volume == :vise
      assert Interlock.holds?(f.ws, :table, :robot, :inside)
      assert run(f, :robot, "DO MOVES VISE") == :done
      assert run(f, :robot, "DO MOVE SAFE") == :done
      assert Interlock.held(f.ws) == []
      no_collisions(f)
    end

    @tag floor: [cycle_ms: 5_000]
    test "refused while the machine holds the table for its cycle", %{f: f} do
      start_cycle(f)
      assert run(f, :robot, "DO APPRO VISE/50") == {:error, "INTERLOCK TABLE HELD BY MONARCH"}
      assert run(f, :robot, "DISABLE_TABLE") == {:error, "INTERLOCK TABLE HELD BY MONARCH"}
      assert robot_at(f) == "SAFE"
      end_cycle(f)
      assert run(f, :robot, "DO APPRO VISE/50") == :done
      no_collisions(f)
    end

    test "refused when the table is not read at park", %{f: f} do
      :ok = Plant.inject_fault(f.plant, :broken_switch, switch: :table_park)

      assert run(f, :robot, "DO APPRO VISE/50") ==
               {:error, "INTERLOCK TABLE NOT IN PARK POSITION"}

      :ok = Plant.clear_fault(f.plant, :all)
      :ok = Plant.inject_fault(f.plant, :sensor_open_circuit, signal: :table_park)

      assert run(f, :robot, "DISABLE_TABLE") ==
               {:error, "INTERLOCK TABLE NO DATA (TABLE SENSOR CH 104 OPEN CIRCUIT)"}

      assert robot_at(f) == "SAFE"
      assert Interlock.held(f.ws) == []
      no_collisions(f)
    end

    @tag floor: [cycle_ms: 5_000]
    test "refused when the machine is active, or its status cannot be read", %{f: f} do
      # a cycle started at the machine's own panel, not by MONARCH
      :ok = GE2000.put_program(f.ge2000, "000100.PRO", "O100\nM30\n")
      assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
      assert run(f, :monarch, "RELEASE_TABLE") == :done
      :ok = GE2000.cycle_start(f.ge2000)

      assert SafetyFloor.wait_until(
               fn -> match?({"ACTIVE", _}, Mailbox.get_device(f.ws, 8)) end,
               2_000
             )

      assert {:error, "INTERLOCK TABLE " <> why} = run(f, :robot, "DO APPRO VISE/50")
      assert why in ["MACHINE ACTIVE", "NOT IN PARK POSITION"]
      GE2000.end_cycle(f.ge2000)

      assert SafetyFloor.wait_until(
               fn -> match?({"IDLE", _}, Mailbox.get_device(f.ws, 8)) end,
               2_000
             )

      # the GE-2000 stops answering: its status grows old and is not trusted
      :ok = GE2000.set_fault(f.ge2000, :silent)
      assert SafetyFloor.wait_until(fn -> elem(Mailbox.get_device(f.ws, 8), 1) > 600 end, 2_000)

      assert {:error, "INTERLOCK TABLE MACHINE STATUS STALE (" <> _} =
               run(f, :robot, "DO APPRO VISE/50")

      assert robot_at(f) == "SAFE"
      no_collisions(f)
    end
  end

  # DRIP_FEED (ours) runs the machine as CYCLE_START does: the interlock table gives it the same
  # rule. Before, it ran the program around an arm inside the machine while MONARCH said IDLE.
  describe "1b and 3b hold for a drip feed as for a cycle start" do
    defp with_nc_file(f) do
      lines = ["%", "O4711"] ++ for(i <- 1..40, do: "N#{i} G01 X#{i}.0 F300") ++ ["M30", "%"]
      :ok = Mailbox.put_nc_file(f.ws, lines)
    end

    test "refused while the arm is inside the machine; the machine runs nothing", %{f: f} do
      with_nc_file(f)
      assert run(f, :robot, "DISABLE_TABLE") == :done
      assert run(f, :robot, "DO APPRO VISE/50") == :done
      assert run(f, :robot, "DO MOVES VISE") == :done
      assert run(f, :monarch, "DRIP_FEED") == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
      assert GE2000.drip(f.ge2000) == nil
      assert GE2000.state(f.ge2000).cycles == 0
      refute Interlock.holds?(f.ws, :table, :monarch)
      no_collisions(f)
    end

    test "refused while the vise holds the table", %{f: f} do
      with_nc_file(f)
      assert run(f, :fixture, "DISABLE_TABLE") == :done
      assert run(f, :monarch, "DRIP_FEED") == {:error, "INTERLOCK TABLE HELD BY FIXTURE"}
      assert GE2000.drip(f.ge2000) == nil
      no_collisions(f)
    end

    test "allowed with the table free; then the machine keeps it until RELEASE_TABLE", %{f: f} do
      with_nc_file(f)
      assert run(f, :monarch, "DRIP_FEED") == :done
      assert GE2000.drip(f.ge2000) != nil
      assert Interlock.holds?(f.ws, :table, :monarch, :cycle)
      assert run(f, :robot, "DO APPRO VISE/50") == {:error, "INTERLOCK TABLE HELD BY MONARCH"}
      assert run(f, :fixture, "OPEN") == {:error, "INTERLOCK TABLE HELD BY MONARCH"}
      assert robot_at(f) == "SAFE"

      assert SafetyFloor.wait_until(
               fn -> run(f, :monarch, "RELEASE_TABLE") == :done end,
               15_000
             )

      assert run(f, :robot, "DO APPRO VISE/50") == :done
      no_collisions(f)
    end
  end

  describe "1b: a cycle starts only once the robot has released the table" do
    test "allowed once the robot has released it and left", %{f: f} do
      assert run(f, :robot, "DISABLE_TABLE") == :done
      assert run(f, :robot, "DO APPRO VISE/50") == :done
      assert run(f, :robot, "DO MOVE SAFE") == :done
      assert run(f, :robot, "RELEASE_TABLE") == :done
      start_cycle(f)
      no_collisions(f)
    end

    test "refused while the robot has disabled the table", %{f: f} do
      assert run(f, :robot, "DISABLE_TABLE") == :done
      assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
      assert GE2000.state(f.ge2000).cycles == 0
      no_collisions(f)
    end

    test "refused while the arm is in the table's volume, which it cannot release", %{f: f} do
      assert run(f, :robot, "DO APPRO VISE/50") == :done
      assert run(f, :robot, "RELEASE_TABLE") == {:error, "INTERLOCK ROBOT IN TABLE VOLUME"}
      assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
      # a DEPART stays in the volume: still refused
      assert run(f, :robot, "DO DEPARTS 50") == :done
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
      assert GE2000.state(f.ge2000).cycles == 0
      assert run(f, :robot, "DO MOVE SAFE") == :done
      start_cycle(f)
      no_collisions(f)
    end

    test "the lease outlives a restart of ROBOT", %{f: f} do
      assert run(f, :robot, "DISABLE_TABLE") == :done
      pid = Vws.CEC.Partition.whereis(f.ws, :robot)
      Process.exit(pid, :kill)

      assert SafetyFloor.wait_until(
               fn -> Vws.CEC.Partition.whereis(f.ws, :robot) not in [nil, pid] end,
               2_000
             )

      assert Interlock.holders(f.ws, :table) == [:robot]
      assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
      assert run(f, :robot, "RELEASE_TABLE") == :done
      start_cycle(f)
      no_collisions(f)
    end
  end

  describe "2a: the robot approaches a tray only once the MHS has released it" do
    test "allowed with the tray at rest", %{f: f} do
      assert MHS.move(f.mhs, 1, :out) == :ok
      assert MHS.move(f.mhs, 1, :in) == :ok
      assert run(f, :robot, "DO APPRO TRAY1/50") == :done
      assert run(f, :robot, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)") == :done
      assert Interlock.holders(f.ws, :tray1) == [:robot]
      no_collisions(f)
    end

    # a roller table that takes 5 s, so both of the robot's requests meet the tray moving (0.6 s
    # let a loaded machine see it arrive before the second)
    @tag floor: [plant: [config: %{motion: %{tray_s: 5_000.0}}]]
    test "refused while the MHS moves the tray", %{f: f} do
      :ok = MHS.request(f.mhs, 1, :out)
      assert SafetyFloor.wait_until(fn -> Plant.snapshot(f.plant).trays[1].moving end, 1_000)
      assert run(f, :robot, "DO APPRO TRAY1/50") == {:error, "INTERLOCK TRAY1 HELD BY MHS"}
      assert run(f, :robot, "DISABLE_TRAY1") == {:error, "INTERLOCK TRAY1 HELD BY MHS"}
      assert robot_at(f) == "SAFE"
      # the robot's own tray is not the MHS's
      assert run(f, :robot, "DO APPRO TRAY2/50") == :done
      assert SafetyFloor.wait_until(fn -> not MHS.busy?(f.mhs) end, 20_000)
      assert [%{tray: 1, direction: :out, result: :ok}] = MHS.history(f.mhs)
      no_collisions(f)
    end
  end

  describe "2b: the MHS moves a tray only once the robot has released it" do
    test "allowed after RELEASE_TRAYn with the arm gone", %{f: f} do
      assert run(f, :robot, "DISABLE_TRAY2") == :done
      assert run(f, :robot, "DO APPROS TRAY2/50") == :done
      assert run(f, :robot, "DO MOVE SAFE") == :done
      assert run(f, :robot, "RELEASE_TRAY2") == :done
      assert MHS.move(f.mhs, 2, :out) == :ok
      refute Plant.snapshot(f.plant).trays[2].in_position
      no_collisions(f)
    end

    test "refused by the lease and by the lock relay while the robot has it", %{f: f} do
      assert run(f, :robot, "DISABLE_TRAY1") == :done
      assert Plant.snapshot(f.plant).trays[1].locked
      assert MHS.move(f.mhs, 1, :out) == {:error, "INTERLOCK TRAY1 HELD BY ROBOT"}
      # were it to ignore the lease, the relay still holds the tray
      assert Plant.move_tray(f.plant, 1, :out) == {:error, :locked}
      assert Plant.snapshot(f.plant).trays[1].in_position
      no_collisions(f)
    end

    test "refused while the arm is in the tray's volume, which it cannot release", %{f: f} do
      assert run(f, :robot, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)") == :done
      assert run(f, :robot, "RELEASE_TRAY1") == {:error, "INTERLOCK ROBOT IN TRAY1 VOLUME"}
      assert MHS.move(f.mhs, 1, :out) == {:error, "INTERLOCK TRAY1 HELD BY ROBOT"}
      assert run(f, :robot, "DO MOVE SAFE") == :done
      assert MHS.move(f.mhs, 1, :out) == :ok
      no_collisions(f)
    end

    test "a locked relay refuses the MHS even when the lease is free", %{f: f} do
      # locked as many times as a loaded machine needs (a DAQ #1 that answered neither the
      # write nor the read after it ended one lock ERROR RELAY 209 NOT AS COMMANDED): what is
      # tested is the MHS against a locked relay
      assert SafetyFloor.wait_until(
               fn -> Vws.Partitions.VwsStatus.tray_lock(f.ws, 2, :lock, 500) == :ok end,
               10_000
             )

      assert MHS.move(f.mhs, 2, :out) == {:error, "TRAY 2 LOCKED"}
      assert Interlock.held(f.ws) == []
      no_collisions(f)
    end
  end

  describe "3a: the vise opens only with the machine idle and the table parked" do
    test "allowed: machine idle, table parked, with the robot holding the table", %{f: f} do
      assert run(f, :fixture, "CLOSE") == :done
      assert run(f, :robot, "DISABLE_TABLE") == :done
      assert run(f, :fixture, "OPEN") == :done
      assert Plant.snapshot(f.plant).vise.fully_open
      assert Interlock.holders(f.ws, :table) == [:robot]
      no_collisions(f)
    end

    @tag floor: [cycle_ms: 5_000]
    test "refused during a cycle", %{f: f} do
      assert run(f, :fixture, "CLOSE") == :done
      start_cycle(f)
      assert run(f, :fixture, "OPEN") == {:error, "INTERLOCK TABLE HELD BY MONARCH"}
      assert run(f, :fixture, "DISABLE_TABLE") == {:error, "INTERLOCK TABLE HELD BY MONARCH"}
      assert Plant.snapshot(f.plant).vise.force_n > 1_900
      end_cycle(f)
      assert run(f, :fixture, "OPEN") == :done
      no_collisions(f)
    end

    test "refused when the table or the machine cannot be read", %{f: f} do
      :ok = DAQ.set_fault(f.daq, :mute)
      assert {:error, "INTERLOCK TABLE " <> _} = run(f, :fixture, "CLOSE")
      :ok = DAQ.set_fault(f.daq, :none)
      assert SafetyFloor.wait_until(fn -> run(f, :fixture, "CLOSE") == :done end, 3_000)

      :ok = GE2000.set_fault(f.ge2000, :silent)
      assert SafetyFloor.wait_until(fn -> elem(Mailbox.get_device(f.ws, 8), 1) > 600 end, 2_000)
      assert {:error, "INTERLOCK TABLE MACHINE STATUS STALE (" <> _} = run(f, :fixture, "OPEN")
      assert Plant.snapshot(f.plant).vise.force_n > 1_900
      no_collisions(f)
    end
  end

  describe "3b: a cycle starts only once the vise has released the table" do
    test "allowed after F RELEASE_TABLE", %{f: f} do
      assert run(f, :fixture, "DISABLE_TABLE") == :done
      assert run(f, :fixture, "CLOSE") == :done
      assert run(f, :fixture, "RELEASE_TABLE") == :done
      start_cycle(f)
      no_collisions(f)
    end

    test "refused while the vise holds the table", %{f: f} do
      assert run(f, :fixture, "DISABLE_TABLE") == :done
      assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY FIXTURE"}
      assert GE2000.state(f.ge2000).cycles == 0
      no_collisions(f)
    end

    test "refused after a vise command failed, until the vise is found at rest", %{f: f} do
      :ok = Plant.inject_fault(f.plant, :weak_clamp, where: :vise, force_n: 300)
      assert {:error, "VISE FORCE " <> _} = run(f, :fixture, "CLOSE")
      assert run(f, :monarch, "PROGRAM_SELECT(000100)") == :done
      assert run(f, :monarch, "CYCLE_START") == {:error, "INTERLOCK TABLE HELD BY FIXTURE"}
      assert run(f, :fixture, "RELEASE_TABLE") == :done
      start_cycle(f)
      no_collisions(f)
    end
  end
end
