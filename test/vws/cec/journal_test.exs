defmodule Vws.CEC.JournalTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.CEC.Journal.Log
  alias Vws.Test.{Eventually, WCPeer}

  @moduletag :tmp_dir

  defp start_ws(id, dir, extra \\ [], overrides \\ []) do
    opts =
      Keyword.merge(
        [
          id: id,
          wc: "loopback:wc-#{id}",
          journal: [dir: dir] ++ extra,
          partitions: Vws.Test.Workstation.held_robot()
        ],
        overrides
      )

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

  test "a program DOWNLOAD_HP stored in the library is journaled by its version, not a second " <>
         "copy, and comes back after a restart; from another library directory it says so",
       %{tmp_dir: dir} do
    id = "nc-ref-#{System.unique_integer([:positive])}"
    journal = Path.join(dir, "journal")

    opts = fn library ->
      [
        id: id,
        wc: "loopback:wc-#{id}",
        journal: [dir: journal],
        library: Path.join(dir, library),
        partitions: Vws.Test.Workstation.held_robot()
      ]
    end

    start_supervised!({Workstation, opts.("library")}, id: id)
    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
    program = ["%", "O004711", "N10 G90 G00 X0 Y0", "N20 G01 X63.5 F200", "%"]
    WCPeer.send_string(peer, 60, [{"M", 1, "DOWNLOAD_HP"}])
    assert WCPeer.recv_line(peer) =~ "05A0060"

    for {line, n} <- Enum.with_index(program, 1) do
      WCPeer.send_raw(peer, Vws.Codecs.WC.Reply.encode({:line, n, line}))
      answer = Vws.Codecs.WC.Reply.encode(WCPeer.download_answer(program, n))
      assert WCPeer.recv_line(peer) <> "\r\n" == IO.iodata_to_binary(answer)
    end

    assert WCPeer.status(peer, 61, 35, "MONARCH_CMD") == "0001DONE"

    # the journal holds the library's version, the library the program
    {:ok, bytes, v} = Vws.CEC.Library.read(id, "004711.PRO", :latest)
    assert bytes == Vws.Links.DNC.Program.to_text(program)
    nc_file = :erlang.binary_to_term(File.read!(Path.join(journal, "nc_file")))
    assert nc_file == {:library, "004711.PRO", v.version, v.digest}

    :ok = stop_supervised(id)
    start_supervised!({Workstation, opts.("library")}, id: id)
    assert Mailbox.nc_file(id) == program

    # that version deleted from the library (issue 27): its bytes stay, the NC file is restored
    {:ok, _} = Vws.CEC.Library.delete(id, "004711.PRO", v.version)
    assert Vws.CEC.Library.read(id, "004711.PRO", v.version) == {:error, :deleted}
    :ok = stop_supervised(id)
    start_supervised!({Workstation, opts.("library")}, id: id)
    assert Mailbox.nc_file(id) == program

    # a library that does not hold that version: no NC file, in the log
    :ok = stop_supervised(id)

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        start_supervised!({Workstation, opts.("another library")}, id: id)
      end)

    assert Mailbox.nc_file(id) == []
    assert log =~ "names 004711.PRO version #{v.version} of the program library"
  end

  # the whole workstation killed and started again on the same journal directory, its log kept
  defp restart(id, dir) do
    :ok = stop_supervised(id)
    ExUnit.CaptureLog.capture_log(fn -> start_ws(id, dir) end)
  end

  defp journal_file(dir), do: Path.join(dir, "journal.log")

  # 8 random bytes just after the file's 4-byte header: the first records are lost
  defp damage_after_header(dir) do
    <<head::binary-size(4), rest::binary>> = File.read!(journal_file(dir))

    File.write!(
      journal_file(dir),
      head <> :crypto.strong_rand_bytes(8) <> binary_part(rest, 8, byte_size(rest) - 8)
    )
  end

  defp statuses(id), do: Map.new(Mailbox.partitions(), &{&1, Mailbox.command_status(id, &1)})

  test "a record torn by a power loss mid-write: the statuses it could have changed say so, loudly",
       %{tmp_dir: dir} do
    id = "torn-#{System.unique_integer([:positive])}"
    start_ws(id, dir)
    :ok = Mailbox.dispatch(id, :gripper, 4, "OPEN")
    :ok = Mailbox.finish(id, :gripper, 4, :done)
    :ok = stop_supervised(id)

    # the next record, written over the end mark, half of it on disk
    bin = File.read!(journal_file(dir))
    torn = binary_part(Log.record({:finish, :vacuum, 9, :done}), 0, 20)
    File.write!(journal_file(dir), binary_part(bin, 0, byte_size(bin) - 15) <> torn)

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        start_ws(id, dir)

        for p <- Mailbox.partitions(),
            do: assert(Mailbox.command_status(id, p) == {nil, {:no_data, "JOURNAL DAMAGED"}})
      end)

    assert log =~ "journal of #{inspect(id)} damaged at byte #{byte_size(bin) - 15}"
    assert log =~ ~r/journal of "#{id}" damaged at byte \d+ of \S+: LAST RECORD CUT SHORT/
    assert [aside] = Path.wildcard(Path.join(dir, "journal.damaged-*"))
    assert File.read!(aside) == binary_part(bin, 0, byte_size(bin) - 15) <> torn

    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
    assert WCPeer.status(peer, 1, 1, "GRIPPER_CMD") == "0000NO DATA (JOURNAL DAMAGED)"
    assert WCPeer.status(peer, 2, 1, "Q_CMD") == "0000NO DATA (JOURNAL DAMAGED)"

    # the first string may be the lost last one again (rule 4 cannot tell): acknowledged, not run
    WCPeer.send_string(peer, 3, [{"V", 7, "ON"}])
    assert WCPeer.recv_line(peer) =~ "05A0003"

    assert WCPeer.await_status(peer, 4, "VACUUM_CMD", &(&1 =~ "ERROR")) ==
             "0007ERROR NOT RUN LAST STRING UNKNOWN AFTER JOURNAL DAMAGE SEND AGAIN"

    # sent again under a new number, it runs and its status is known again; the others stay
    # unknown across restarts
    WCPeer.send_string(peer, 5, [{"V", 8, "ON"}])
    assert WCPeer.recv_line(peer) =~ "05A0005"

    assert WCPeer.await_status(peer, 6, "VACUUM_CMD", &(&1 =~ ~r/^0008ERROR/)) ==
             "0008ERROR NO LINK TO DAQ #1"

    WCPeer.close(peer)
    quiet = restart(id, dir)
    refute quiet =~ "journal of #{inspect(id)} damaged"
    assert Mailbox.command_status(id, :vacuum) == {8, {:error, "NO LINK TO DAQ #1"}}
    assert Mailbox.command_status(id, :gripper) == {nil, {:no_data, "JOURNAL DAMAGED"}}
  end

  # A status lost with damaged bytes may have been a command under way (a vise motion): the
  # restarted partition's safe clean-up runs as for an interrupted command. Here FIXTURE's —
  # both vise valves off — with no DAQ to reach, so it gives up quickly and says so.
  test "after damage, a partition whose status is unknown runs its safe clean-up", %{tmp_dir: dir} do
    id = "cleanup-damage-#{System.unique_integer([:positive])}"
    start_ws(id, dir)
    :ok = stop_supervised(id)

    damage_after_header(dir)

    parent = self()
    handler = "cleanup-#{id}"

    Vws.Telemetry.attach(
      handler,
      [:vws, :partition, :cleaned_up],
      fn _event, _m, meta, _ -> send(parent, {:cleaned_up, meta}) end,
      nil
    )

    on_exit(fn -> Vws.Telemetry.detach(handler) end)

    fixture = [options: [cleanup_timeout_ms: 300, cleanup_retry_ms: 50]]

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        start_ws(id, dir, [],
          partitions: Keyword.put(Vws.Test.Workstation.held_robot(), :fixture, fixture)
        )

        assert_receive {:cleaned_up, %{workstation: ^id, partition: :fixture} = meta}, 10_000
        assert meta.text == :unknown
        # no DAQ #1 here: the valves could not be reached, and that is not hidden
        assert {:error, why} = meta.status
        assert is_binary(why)
        Logger.flush()
      end)

    assert Mailbox.command_status(id, :fixture) == {nil, {:no_data, "JOURNAL DAMAGED"}}

    assert log =~
             "status unknown after the damaged journal (a command may have been under way): safe state NOT restored"

    # a partition without a clean-up of its own (the gripper) has nothing to run
    refute_received {:cleaned_up, %{workstation: ^id, partition: :gripper}}
  end

  # A lease taken in the damaged part is not known (the arm may be in the vise): every volume is
  # held by JOURNAL, which shares with nobody, until a person releases it; kept across restarts.
  test "after damage every work volume is held by JOURNAL until released by hand", %{tmp_dir: dir} do
    id = "lease-damage-#{System.unique_integer([:positive])}"
    start_ws(id, dir)
    :ok = Vws.CEC.Interlock.acquire(id, :tray1, :mhs, 0)
    :ok = stop_supervised(id)

    damage_after_header(dir)

    log = ExUnit.CaptureLog.capture_log(fn -> start_ws(id, dir) end)
    assert log =~ "every work volume held by JOURNAL"

    for volume <- [:table, :tray1, :tray2] do
      assert :journal in Vws.CEC.Interlock.holders(id, volume)
    end

    assert Vws.CEC.Interlock.acquire(id, :table, :robot, 0) ==
             {:error, "INTERLOCK TABLE HELD BY JOURNAL"}

    assert Vws.CEC.Interlock.acquire(id, :table, :monarch, 0) ==
             {:error, "INTERLOCK TABLE HELD BY JOURNAL"}

    # kept across a restart until released; the release is journaled like any other
    restart(id, dir)
    assert :journal in Vws.CEC.Interlock.holders(id, :table)
    :ok = Vws.CEC.Interlock.release(id, :table, :journal)
    assert Vws.CEC.Interlock.acquire(id, :table, :robot, 0) == :ok
    restart(id, dir)
    refute :journal in Vws.CEC.Interlock.holders(id, :table)
    assert :journal in Vws.CEC.Interlock.holders(id, :tray2)
  end

  test "the rule-2 string *0001*S0001VISE*G0001OPEN* survives a kill and a stop: the workstation starts again",
       %{tmp_dir: dir} do
    id = "rule2-#{System.unique_integer([:positive])}"
    sup = start_ws(id, dir)
    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
    WCPeer.send_line(peer, Vws.Test.Acceptance.wc_frame("*0001*S0001VISE*G0001OPEN*"))
    assert WCPeer.recv_line(peer) =~ "05A0001"
    expected = "0001ERROR RULE 2 STATUS COMMAND NOT ALONE"
    assert WCPeer.status(peer, 2, 2, "GRIPPER_CMD") == expected
    WCPeer.close(peer)

    Process.exit(sup, :kill)

    assert Eventually.eventually(fn ->
             Workstation.whereis(id) not in [nil, sup] and listening?(id)
           end)

    assert Mailbox.command_status(id, :gripper) ==
             {1, {:error, "RULE 2 STATUS COMMAND NOT ALONE"}}

    log = restart(id, dir)
    refute log =~ "journal of #{inspect(id)} damaged"
    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
    assert WCPeer.status(peer, 3, 3, "GRIPPER_CMD") == expected
    assert WCPeer.status(peer, 4, 4, "VISE_CMD") == "0000NONE"
  end

  defp listening?(id) do
    Vws.CEC.SunComm.listening(id) != nil
  catch
    :exit, _ -> false
  end

  test "records an earlier version wrote restore, the status of set S too (nothing to restore)",
       %{tmp_dir: dir} do
    id = "old-#{System.unique_integer([:positive])}"

    File.write!(
      journal_file(dir),
      Enum.map(
        [
          {:string, 1, "*0001*S0001VISE*G0001OPEN*", [{:gripper, 1}]},
          {:status, :status, 1, {:error, "RULE 2 STATUS COMMAND NOT ALONE"}},
          {:status, :gripper, 1, {:error, "RULE 2 STATUS COMMAND NOT ALONE"}},
          {:status, :fixture, 3, :executing, "OPEN"},
          {:finish, :fixture, 3, :done},
          {:unknown_status, "Q", 5, {:error, "UNKNOWN COMMAND SET Q"}}
        ],
        &Log.record/1
      ) ++ [Log.end_mark()]
    )

    log = ExUnit.CaptureLog.capture_log(fn -> start_ws(id, dir) end)
    refute log =~ "journal of #{inspect(id)} damaged"

    assert Mailbox.command_status(id, :gripper) ==
             {1, {:error, "RULE 2 STATUS COMMAND NOT ALONE"}}

    assert Mailbox.command_status(id, :fixture) == {3, :done}
    assert Mailbox.cmd_in(id, :fixture) == {3, "OPEN"}
    assert Mailbox.unknown_status(id, "Q") == {5, {:error, "UNKNOWN COMMAND SET Q"}}
    assert Mailbox.unknown_status(id, "Z") == {nil, :none}
    assert Mailbox.last_string(id) == {1, "*0001*S0001VISE*G0001OPEN*"}
    assert Path.wildcard(Path.join(dir, "journal.damaged-*")) == []
  end

  test "an empty or random journal starts with every status unknown, in words, and is kept aside",
       %{tmp_dir: dir} do
    for {content, n} <- [{"", 1}, {:crypto.strong_rand_bytes(3_000), 2}] do
      id = "random-#{n}-#{System.unique_integer([:positive])}"
      jdir = Path.join(dir, "#{n}")
      File.mkdir_p!(jdir)
      File.write!(journal_file(jdir), content)
      log = ExUnit.CaptureLog.capture_log(fn -> start_ws(id, jdir) end)
      assert log =~ "journal of #{inspect(id)} damaged at byte 0"
      assert log =~ "a copy is kept as #{jdir}/journal.damaged-"

      assert statuses(id) ==
               Map.new(Mailbox.partitions(), &{&1, {nil, {:no_data, "JOURNAL DAMAGED"}}})

      assert Mailbox.unknown_status(id, "Q") == {nil, {:no_data, "JOURNAL DAMAGED"}}
      assert [_] = Path.wildcard(Path.join(jdir, "journal.damaged-*"))
      # the WC link and the partitions work
      :ok = Mailbox.dispatch(id, :gripper, 1, "OPEN")
      :ok = Mailbox.finish(id, :gripper, 1, :done)
      assert Mailbox.command_status(id, :gripper) == {1, :done}
      :ok = stop_supervised(id)
    end
  end

  test "a random or empty journal.1 of the old disk_log format: started with everything unknown",
       %{tmp_dir: dir} do
    for {content, n} <- [{"", 1}, {:crypto.strong_rand_bytes(3_000), 2}] do
      id = "oldrandom-#{n}-#{System.unique_integer([:positive])}"
      jdir = Path.join(dir, "#{n}")
      File.mkdir_p!(jdir)
      File.write!(Path.join(jdir, "journal.1"), content)
      log = ExUnit.CaptureLog.capture_log(fn -> start_ws(id, jdir) end)
      assert log =~ "journal of #{inspect(id)} damaged at byte"
      assert Mailbox.command_status(id, :vacuum) == {nil, {:no_data, "JOURNAL DAMAGED"}}
      assert [_] = Path.wildcard(Path.join(jdir, "journal.disk_log-*"))
      refute File.exists?(Path.join(jdir, "journal.1"))
      :ok = stop_supervised(id)
    end
  end

  test "a journal of the old disk_log format, left by kill -9, is read once and moved aside",
       %{tmp_dir: dir} do
    name = {:old_format, make_ref()}

    {:ok, ^name} =
      :disk_log.open(
        name: name,
        file: String.to_charlist(Path.join(dir, "journal")),
        type: :wrap,
        size: {64 * 1024, 4}
      )

    :ok =
      :disk_log.log(
        name,
        {:snapshot,
         %{
           partitions:
             Map.new(
               Mailbox.partitions(),
               &{&1, %{number: nil, status: :none, cmd_in: {nil, nil}}}
             ),
           last_string: {nil, nil}
         }}
      )

    :ok = :disk_log.log(name, {:status, :vacuum, 3, :executing, "ON"})
    :ok = :disk_log.log(name, {:finish, :vacuum, 3, :done})
    :ok = :disk_log.sync(name)

    # killed as by kill -9: the log is not closed, the next open must repair it (the log is
    # linked to its opener, this test)
    Process.flag(:trap_exit, true)

    [log_pid] =
      for {_, pid, _, _} <- Supervisor.which_children(:disk_log_sup),
          :disk_log.pid2name(pid) == {:ok, name},
          do: pid

    Process.exit(log_pid, :kill)

    id = "oldformat-#{System.unique_integer([:positive])}"
    ExUnit.CaptureLog.capture_log(fn -> start_ws(id, dir) end)
    assert Mailbox.command_status(id, :vacuum) == {3, :done}
    assert Mailbox.command_status(id, :robot) == {nil, :none}
    assert File.exists?(journal_file(dir))
    refute File.exists?(Path.join(dir, "journal.1"))
  end

  test "a lease whose atoms do not exist yet when the journal opens (their modules not loaded) restores",
       %{tmp_dir: dir} do
    # a record naming an atom this VM has never seen: written with a placeholder, renamed
    placeholder = :journal_test_placeholder_reason
    fresh = "r" <> Base.encode32(:crypto.strong_rand_bytes(25), case: :lower, padding: false)
    fresh = binary_part(fresh, 0, byte_size(Atom.to_string(placeholder)))
    bin = :erlang.term_to_binary({:lease, :table, :robot, [placeholder]})
    bin = :binary.replace(bin, Atom.to_string(placeholder), fresh)
    File.write!(journal_file(dir), [Log.frame(1, bin), Log.end_mark()])

    id = "atoms-#{System.unique_integer([:positive])}"
    log = ExUnit.CaptureLog.capture_log(fn -> start_ws(id, dir) end)
    refute log =~ "journal of #{inspect(id)} damaged"

    assert [%{volume: :table, holder: :robot, reasons: [reason]}] = Vws.CEC.Interlock.held(id)
    assert Atom.to_string(reason) == fresh
  end

  test "a record this version cannot apply: only what it could have changed is unknown",
       %{tmp_dir: dir} do
    id = "newer-#{System.unique_integer([:positive])}"

    frames = [
      Log.record({:status, :fixture, 3, :executing, "OPEN"}),
      Log.record({:status, :vacuum, 4, :done}),
      # a status of a shape this version does not know: its partition only
      Log.record({:status, :vacuum, 5, {:paused, 3}}),
      Log.record({:status, :gripper, 6, :done}),
      # a frame of a kind a newer version writes: anything could have changed
      Log.frame(7, "whatever a newer version says"),
      Log.record({:status, :gripper, 8, {:error, "X"}}),
      Log.end_mark()
    ]

    File.write!(journal_file(dir), frames)
    log = ExUnit.CaptureLog.capture_log(fn -> start_ws(id, dir) end)
    assert log =~ ~r/journal of "#{id}" damaged at byte \d+ of \S+: RECORD OF UNKNOWN SHAPE/
    assert log =~ ~r/journal of "#{id}" damaged at byte \d+ of \S+: FRAME OF UNKNOWN KIND 7/
    assert Mailbox.command_status(id, :gripper) == {8, {:error, "X"}}
    unreadable = {nil, {:no_data, "JOURNAL RECORD UNREADABLE"}}
    assert Mailbox.command_status(id, :vacuum) == unreadable
    assert Mailbox.command_status(id, :fixture) == unreadable
    assert Mailbox.command_status(id, :robot) == unreadable

    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
    assert WCPeer.status(peer, 1, 1, "FIXTURE_CMD") == "0000NO DATA (JOURNAL RECORD UNREADABLE)"
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

    assert File.stat!(journal_file(dir)).size < 4_000 + 1_000

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
