defmodule Vws.Reliability.JournalFullDiskTest do
  # Issue 30, "Durable or refused, never in between": the journal on a small tmpfs, filled. A
  # command whose record cannot be written never reads DONE; the node takes no string until
  # space returns and a fresh snapshot is written; no torn record stays in the log; what was
  # acknowledged before, during and after survives a kill.
  use ExUnit.Case, async: true

  alias Vws.CEC.{Journal, Mailbox, Workstation}
  alias Vws.CEC.Journal.Log
  alias Vws.Test.{Eventually, WCPeer}

  @root? match?({"0\n", 0}, System.cmd("id", ["-u"]))
  unless @root?, do: @moduletag(skip: "needs root to mount a tmpfs")

  @moduletag :tmp_dir
  @moduletag timeout: 120_000

  setup %{tmp_dir: dir} do
    mnt = Path.join(dir, "small")
    File.mkdir_p!(mnt)
    {_, 0} = System.cmd("mount", ["-t", "tmpfs", "-o", "size=128k", "tmpfs", mnt])
    on_exit(fn -> System.cmd("umount", ["-l", mnt]) end)
    %{mnt: mnt}
  end

  defp start_ws(id, dir) do
    opts = [
      id: id,
      wc: "loopback:wc-#{id}",
      journal: [dir: dir, retry_ms: 100],
      partitions: Vws.Test.Workstation.held_robot()
    ]

    start_supervised!({Workstation, opts}, id: id)
  end

  # fills the file system: 4 KiB at a time until it is full
  defp fill(mnt) do
    {:ok, fd} = :file.open(Path.join(mnt, "filler"), [:write, :raw, :binary])
    chunk = :binary.copy(<<0>>, 4096)
    Stream.repeatedly(fn -> :file.write(fd, chunk) end) |> Enum.find(&(&1 != :ok))
    :file.close(fd)
  end

  defp vacuum_status(peer, seq, n) do
    WCPeer.await_status(peer, seq, "VACUUM_CMD", fn text ->
      text =~ ~r/^#{Vws.Codecs.WC.Command.pad4(n)}(DONE|ERROR)/
    end)
  end

  test "a full disk: ERROR JOURNAL WRITE FAILED, never DONE; strings refused; space back, a fresh snapshot, work again",
       %{mnt: mnt} do
    id = "fulldisk-#{System.unique_integer([:positive])}"
    jdir = Path.join(mnt, "journal")
    sup = start_ws(id, jdir)
    {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")

    WCPeer.send_string(peer, 1, [{"V", 1, "ON"}])
    assert WCPeer.recv_line(peer) =~ "05A0001"
    assert vacuum_status(peer, 1, 1) == "0001ERROR NO LINK TO DAQ #1"

    fill(mnt)

    # commands until the journal cannot take a record: the string is refused (E), or the
    # command's dispatch or end is not on disk and it ends ERROR JOURNAL WRITE FAILED
    log =
      ExUnit.CaptureLog.capture_log(fn ->
        outcome =
          Enum.find_value(2..200, fn n ->
            WCPeer.send_string(peer, n, [{"V", n, "ON"}])

            case WCPeer.recv_line(peer) do
              "E" ->
                {:refused, n}

              ack ->
                assert ack =~ "05A#{Vws.Codecs.WC.Command.pad4(n)}"
                status = vacuum_status(peer, n, n)
                refute status =~ "DONE"

                if status =~ "ERROR JOURNAL WRITE FAILED",
                  do: {:failed, n},
                  else:
                    (
                      assert status =~ "ERROR NO LINK TO DAQ #1"
                      nil
                    )
            end
          end)

        assert {_, n} = outcome
        assert {:error, health} = Journal.health(id)
        assert health =~ "JOURNAL WRITE FAILED AT"

        # the node takes no work: a new string is refused, a status is still answered
        WCPeer.send_string(peer, 300, [{"G", 300, "OPEN"}])
        assert WCPeer.recv_line(peer) == "E"
        assert Mailbox.command_status(id, :gripper) == {nil, :none}
        assert WCPeer.status(peer, 301, 1, "GRIPPER_CMD") == "0000NONE"
        send(self(), {:last, n})
      end)

    assert log =~
             ~r/journal of "#{id}": write failed \(no space left on device\): .* \(ERROR JOURNAL WRITE FAILED\)/

    assert log =~ ~r/journal of "#{id}" not healthy since .*: string 0300 refused/
    assert_received {:last, last}

    # no torn record in the log: it ends whole, with its end mark
    bin = File.read!(Path.join(jdir, "journal.log"))
    assert Enum.all?(Log.parse(bin), &match?({:record, _, _}, &1))

    # space again: a fresh snapshot, then work
    log =
      ExUnit.CaptureLog.capture_log(fn ->
        File.rm!(Path.join(mnt, "filler"))
        assert Eventually.eventually(fn -> Journal.health(id) == :ok end, 10_000)
      end)

    assert log =~ "journal of #{inspect(id)} healthy again"
    n = last + 1
    WCPeer.send_string(peer, n, [{"V", n, "ON"}])
    assert WCPeer.recv_line(peer) =~ "05A#{Vws.Codecs.WC.Command.pad4(n)}"
    assert vacuum_status(peer, n, n) == "#{Vws.Codecs.WC.Command.pad4(n)}ERROR NO LINK TO DAQ #1"
    WCPeer.close(peer)

    # and it is on disk: killed, started again, the same answer, nothing damaged
    Process.exit(sup, :kill)

    assert Eventually.eventually(fn ->
             Workstation.whereis(id) not in [nil, sup] and
               try do
                 Vws.CEC.SunComm.listening(id) != nil
               catch
                 :exit, _ -> false
               end
           end)

    assert Mailbox.command_status(id, :vacuum) == {n, {:error, "NO LINK TO DAQ #1"}}
    assert Mailbox.last_string(id) |> elem(0) == n
    assert Path.wildcard(Path.join(jdir, "journal.damaged-*")) == []
  end
end
