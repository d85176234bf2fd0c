defmodule Vws.CEC.JournalTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.Test.{Eventually, WCPeer}

  @moduletag :tmp_dir

  defp start_ws(id, dir, extra \\ []) do
    opts = [
      id: id,
      wc: "loopback:wc-#{id}",
      journal: [dir: dir] ++ extra,
      partitions: Vws.Test.Workstation.held_robot()
    ]

    start_supervised!({Workstation, opts}, id: id)
  end

  test "a killed workstation comes back with every command status true; nothing re-runs",
       %{tmp_dir: dir} do
    id = "journal-#{System.unique_integer([:positive])}"
    sup = start_ws(id, dir)
    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")

    # the vacuum command finishes (no link: ERROR), the robot command stays in flight
    WCPeer.send_string(peer, 41, [{"V", 7, "ON"}])
    assert WCPeer.recv_line(peer) =~ "05A0041"

    assert WCPeer.await_status(peer, 1, "VACUUM_CMD", &(&1 =~ "ERROR")) ==
             "0007ERROR NO LINK TO DAQ #1"

    line = WCPeer.send_string(peer, 42, [{"R", 9, "HOLD"}])
    assert WCPeer.recv_line(peer) =~ "05A0042"
    assert_receive {:executing, _runner, 9, _}, 5_000

    # the whole workstation dies; its supervisor (here the test's) starts it again
    Process.exit(sup, :kill)

    assert Eventually.eventually(fn ->
             case Workstation.whereis(id) do
               pid when is_pid(pid) and pid != sup ->
                 try do
                   Vws.CEC.SunComm.listening(id) != nil
                 catch
                   :exit, _ -> false
                 end

               _ ->
                 false
             end
           end)

    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
    assert WCPeer.status(peer, 43, 2, "ROBOT_CMD") == "0009ERROR INTERRUPTED BY RESTART"
    assert WCPeer.status(peer, 44, 3, "VACUUM_CMD") == "0007ERROR NO LINK TO DAQ #1"
    assert Mailbox.cmd_in(id, :robot) == {9, "HOLD"}
    refute_receive {:executing, _, 9, _}, 200

    # the WC never got the acknowledgement and resends: it is a retransmission, not run
    WCPeer.send_raw(peer, line)
    assert WCPeer.recv_line(peer) =~ "05A0042"
    refute_receive {:executing, _, _, _}, 200
    assert WCPeer.status(peer, 45, 4, "ROBOT_CMD") == "0009ERROR INTERRUPTED BY RESTART"
  end

  test "the work-volume leases come back after a kill, through the compacted journal too",
       %{tmp_dir: dir} do
    id = "leases-#{System.unique_integer([:positive])}"
    sup = start_ws(id, dir)

    :ok = Vws.CEC.Interlock.acquire(id, :table, :robot, 0, as: :disabled)
    :ok = Vws.CEC.Interlock.acquire(id, :table, :robot, 0, as: :inside)
    :ok = Vws.CEC.Interlock.acquire(id, :table, :fixture, 0, as: :vise)
    :ok = Vws.CEC.Interlock.acquire(id, :tray1, :robot, 0)
    :ok = Vws.CEC.Interlock.release(id, :tray1, :robot)
    :ok = Vws.CEC.Interlock.release(id, :table, :robot, :inside)

    Process.exit(sup, :kill)
    # the new supervisor is registered before its children start: wait for the whole workstation
    assert Eventually.eventually(fn ->
             Workstation.whereis(id) not in [nil, sup] and
               try do
                 Vws.CEC.SunComm.listening(id) != nil
               catch
                 :exit, _ -> false
               end
           end)

    held = fn -> Enum.map(Vws.CEC.Interlock.held(id), &{&1.volume, &1.holder, &1.reasons}) end
    assert held.() == [{:table, :robot, [:disabled]}, {:table, :fixture, [:vise]}]

    assert Vws.CEC.Interlock.acquire(id, :table, :monarch, 0) ==
             {:error, "INTERLOCK TABLE HELD BY ROBOT"}

    # the journal was compacted to a snapshot when it opened: the next restart reads that
    :ok = stop_supervised(id)
    start_ws(id, dir)
    assert held.() == [{:table, :robot, [:disabled]}, {:table, :fixture, [:vise]}]
  end

  test "a torn last record is cut off and the records before it are kept", %{tmp_dir: dir} do
    id = "torn-#{System.unique_integer([:positive])}"
    start_ws(id, dir)
    :ok = Mailbox.dispatch(id, :gripper, 4, "OPEN")
    :ok = Mailbox.finish(id, :gripper, 4, :done)

    # power lost: the log process dies without closing its files …
    [log_pid] =
      for {_, pid, _, _} <- Supervisor.which_children(:disk_log_sup),
          :disk_log.pid2name(pid) == {:ok, {:vws_journal, id}},
          do: pid

    Process.exit(log_pid, :kill)
    :ok = stop_supervised(id)

    # … in the middle of writing one more record
    [current] = Path.wildcard(Path.join(dir, "journal.[0-9]*"))
    File.write!(current, <<0, 0, 0, 40, 0x12, 0x34, 0x56, 0x78, 131, 104, 4>>, [:append])

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        start_ws(id, dir)
        assert Mailbox.command_status(id, :gripper) == {4, :done}
      end)

    assert log =~ "repaired" or log =~ "unreadable"

    # and the next restart finds the journal whole again (it was compacted on open)
    :ok = Mailbox.dispatch(id, :gripper, 5, "CLOSE")
    :ok = stop_supervised(id)

    quiet =
      ExUnit.CaptureLog.capture_log(fn ->
        start_ws(id, dir)
        assert Mailbox.command_status(id, :gripper) == {5, {:error, "INTERRUPTED BY RESTART"}}
      end)

    refute quiet =~ "unreadable"
  end

  test "the journal is bounded and the newest state survives the wrap", %{tmp_dir: dir} do
    id = "wrap-#{System.unique_integer([:positive])}"
    start_ws(id, dir, max_bytes: 4_000, max_files: 3, snapshot_every: 20)

    for n <- 1..400 do
      :ok = Mailbox.dispatch(id, :vacuum, n, "ON")

      :ok =
        Mailbox.finish(id, :vacuum, n, if(rem(n, 2) == 0, do: :done, else: {:error, "ODD #{n}"}))
    end

    :ok = Mailbox.dispatch(id, :robot, 77, "WHERE")
    :ok = stop_supervised(id)

    sizes = for f <- Path.wildcard(Path.join(dir, "journal.*")), do: File.stat!(f).size
    assert Enum.sum(sizes) < 4 * 4_000 + 1_000

    start_ws(id, dir)
    assert Mailbox.command_status(id, :vacuum) == {400, :done}
    assert Mailbox.command_status(id, :robot) == {77, {:error, "INTERRUPTED BY RESTART"}}
  end

  test "a journal directory held by another live OS process is not used; one left by a dead one is",
       %{tmp_dir: dir} do
    # another OS process holds the directory
    port = Port.open({:spawn_executable, System.find_executable("sleep")}, args: ["60"])
    {:os_pid, os_pid} = Port.info(port, :os_pid)
    File.write!(Path.join(dir, "LOCK"), Integer.to_string(os_pid))
    id = "journal-lock-#{System.unique_integer([:positive])}"

    assert {:error, _} =
             start_supervised(
               {Workstation, id: id, wc: "loopback:wc-#{id}", journal: [dir: dir]},
               id: id
             )

    # it is gone (kill -9): the directory is taken over
    {_, 0} = System.cmd("kill", ["-9", Integer.to_string(os_pid)])
    assert Eventually.eventually(fn -> Port.info(port) == nil end)
    start_ws(id, dir)
    assert File.read!(Path.join(dir, "LOCK")) == System.pid()
  end
end
