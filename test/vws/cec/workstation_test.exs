defmodule Vws.CEC.WorkstationTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, Partition}
  alias Vws.Test.{WCPeer, Workstation, Eventually}
  alias Vws.CEC.Workstation, as: WS

  test "VWS_CONTROL starts every partition, causes OK_TO_PROCEED, then SUN_COMM" do
    %{ws: ws} = Workstation.start()
    for p <- [:vws_status | Mailbox.partitions()], do: assert(is_pid(Partition.whereis(ws, p)))
    assert Vws.CEC.Events.count(ws, :ok_to_proceed) == 1
    assert Vws.CEC.SunComm.info(ws).ok_to_proceed
    assert ws in WS.list()
  end

  test "device statuses say whether a device has no link or has not been read yet" do
    %{ws: ws} = Workstation.start(devices: [robot: "loopback:no-robot-here"])
    assert Mailbox.get_device(ws, 9) |> elem(0) == "NO DATA (VAL II NOT READ YET)"
    assert Mailbox.get_device(ws, 8) |> elem(0) == "NO DATA (NO LINK TO GE-2000)"
  end

  test "several workstations run side by side on one node, each with its own mailboxes" do
    %{ws: a, wc: wc_a} = Workstation.start()
    %{ws: b, wc: wc_b} = Workstation.start()
    {:ok, pa} = WCPeer.connect(wc_a)
    {:ok, pb} = WCPeer.connect(wc_b)
    WCPeer.send_string(pa, 1, [{"V", 3, "ON"}])
    assert WCPeer.recv_line(pa) =~ "05A0001"

    assert Eventually.eventually(fn ->
             match?({3, {:error, _}}, Mailbox.command_status(a, :vacuum))
           end)

    assert Mailbox.command_status(b, :vacuum) == {nil, :none}
    assert WCPeer.status(pb, 2, 1, "VACUUM_CMD") == "0000NONE"
  end

  test "a workstation can be started and stopped at run time" do
    id = "runtime-#{System.unique_integer([:positive])}"
    {:ok, _} = WS.start(id: id, wc: "loopback:rt-#{id}")
    assert id in WS.list()
    :ok = WS.stop(id)
    assert Eventually.eventually(fn -> id not in WS.list() and not Mailbox.exists?(id) end)
  end

  describe "crash isolation" do
    setup do
      %{ws: ws, wc: wc} = Workstation.start(partitions: Workstation.held_robot())
      {:ok, peer} = WCPeer.connect(wc)
      %{ws: ws, peer: peer, sun_comm: WS.whereis(ws, :sun_comm)}
    end

    test "a partition killed mid-command restarts alone; its command ends ERROR and is not re-run",
         %{ws: ws, peer: peer, sun_comm: sun_comm} do
      WCPeer.send_string(peer, 1, [{"R", 9, "HOLD"}])
      assert WCPeer.recv_line(peer) =~ "05A0001"
      assert_receive {:executing, runner, 9, _}, 5_000
      ref = Process.monitor(runner)

      old = Partition.whereis(ws, :robot)
      Process.exit(old, :kill)
      # the physical action dies with its partition
      assert_receive {:DOWN, ^ref, :process, ^runner, _}, 5_000

      assert Eventually.eventually(fn -> Partition.whereis(ws, :robot) not in [nil, old] end)

      # the name is registered before init/1 has run: wait for the restarted partition's verdict
      assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ "ERROR")) ==
               "0009ERROR INTERRUPTED BY PARTITION RESTART"

      refute_receive {:executing, _, 9, _}, 200
      assert Partition.info(ws, :robot).restarts == 1

      # SUN_COMM and its connection never noticed
      assert WS.whereis(ws, :sun_comm) == sun_comm
      assert Vws.CEC.SunComm.info(ws).counters.connections == 1

      # and the partition takes new commands
      WCPeer.send_string(peer, 3, [{"R", 10, "HOLD"}])
      assert WCPeer.recv_line(peer) =~ "05A0003"
      assert_receive {:executing, runner, 10, _}, 5_000
      send(runner, {:result, :done})
      assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 == "0010DONE")) == "0010DONE"
    end

    test "every partition and every link process can be killed; SUN_COMM stays",
         %{ws: ws, peer: peer, sun_comm: sun_comm} do
      for p <- [:vws_status | Mailbox.partitions()] do
        pid = Partition.whereis(ws, p)
        Process.exit(pid, :kill)

        assert Eventually.eventually(fn -> Partition.whereis(ws, p) not in [nil, pid] end),
               "#{p} restarted"

        assert WCPeer.status(peer, 5, 1, "GRIPPER_CMD") == "0000NONE"
      end

      for {id, pid, _, _} <- Supervisor.which_children(WS.whereis(ws, :links)), is_pid(pid) do
        Process.exit(pid, :kill)

        assert Eventually.eventually(fn ->
                 Enum.any?(Supervisor.which_children(WS.whereis(ws, :links)), fn {i, p, _, _} ->
                   i == id and is_pid(p) and p != pid
                 end)
               end)
      end

      assert WS.whereis(ws, :sun_comm) == sun_comm
      assert WCPeer.status(peer, 6, 1, "ROBOT_CMD") == "0000NONE"
      assert Vws.CEC.SunComm.info(ws).counters.connections == 1
    end

    test "a command that crashes ends ERROR with the reason and the partition goes on",
         %{ws: ws, peer: peer} do
      pid = Partition.whereis(ws, :robot)
      WCPeer.send_string(peer, 7, [{"R", 11, "CRASH"}])
      assert WCPeer.recv_line(peer) =~ "05A0007"
      assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ "ERROR")) =~ "0011ERROR CRASHED"
      assert Partition.whereis(ws, :robot) == pid
    end
  end

  test "equipment outside the CEC takes work volumes in its own name only" do
    %{ws: ws} = Workstation.start()
    assert WS.acquire_volume(ws, :tray1, :mhs, 0) == :ok
    assert Vws.CEC.Interlock.holder(ws, :tray1) == :mhs
    assert WS.acquire_volume(ws, :tray1, :mhs, 0) == :ok
    # never a partition's name: the MHS cannot take or give back the robot's lease
    assert_raise FunctionClauseError, fn -> WS.acquire_volume(ws, :table, :robot, 0) end
    assert_raise FunctionClauseError, fn -> WS.release_volume(ws, :tray1, :robot) end
    assert WS.release_volume(ws, :tray1, :mhs) == :ok
    assert Vws.CEC.Interlock.held(ws) == []

    assert WS.acquire_volume("no-such-workstation", :tray1, :mhs, 0) ==
             {:error, "NO ANSWER FROM THE CEC"}
  end
end
