defmodule Vws.CEC.SunCommTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, Events}
  alias Vws.Codecs.WC.ProgramCRC
  alias Vws.Test.{WCPeer, Workstation}
  import Vws.Test.Eventually

  defp ack?(line, seq), do: Vws.Codecs.WC.Reply.decode(line) == {:ok, {:ack, seq}}

  # NC program line `n` on the wire, and the answer that says it was stored
  defp nc(n, text), do: Vws.Codecs.WC.Reply.encode({:line, n, text})

  defp stored(n),
    do: IO.iodata_to_binary(Vws.Codecs.WC.Reply.encode({:line_ack, n})) |> String.trim()

  # the answer to line `n` of `program`: the closing `%` names the count and the CRC
  defp answer(program, n),
    do:
      IO.iodata_to_binary(Vws.Codecs.WC.Reply.encode(WCPeer.download_answer(program, n)))
      |> String.trim()

  # UPLOAD_SUN's closing line text: `%/cccc`
  defp closing(program),
    do: Vws.Codecs.WC.ProgramCRC.closing_line(List.last(program), ProgramCRC.compute(program))

  setup context do
    partitions = if context[:held], do: Workstation.held_robot(), else: []

    sun_comm =
      if context[:takeover_after], do: [takeover_after: context[:takeover_after]], else: []

    %{ws: ws, wc: wc} = Workstation.start(partitions: partitions, sun_comm: sun_comm)
    {:ok, peer} = WCPeer.connect(wc)
    %{ws: ws, peer: peer, wc: wc}
  end

  test "an intact string is acknowledged 05A with its sequence number", %{peer: peer} do
    WCPeer.send_string(peer, 54, [{"G", 4, "OPEN"}])
    assert ack?(WCPeer.recv_line(peer), 54)
  end

  test "a string with a bad BCC, and garbage, are answered E", %{peer: peer, ws: ws} do
    line = WCPeer.string(54, [{"G", 4, "OPEN"}])
    [body, _bcc] = Regex.run(~r/^(.*\*)(\d{3})\r\n$/, line, capture: :all_but_first)
    wrong = body <> "999\r\n"
    WCPeer.send_raw(peer, wrong)
    assert WCPeer.recv_line(peer) == "E"
    WCPeer.send_line(peer, "hello")
    assert WCPeer.recv_line(peer) == "E"
    # nothing ran
    assert Mailbox.command_status(ws, :gripper) == {nil, :none}
  end

  test "status before any command answers NONE", %{peer: peer} do
    assert WCPeer.status(peer, 1, 39, "ROBOT_CMD") == "0000NONE"
  end

  test "a command without its device link ends ERROR NO LINK", %{peer: peer} do
    WCPeer.send_string(peer, 54, [
      {"R", 9, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"},
      {"G", 4, "OPEN"}
    ])

    assert ack?(WCPeer.recv_line(peer), 54)

    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ "ERROR")) ==
             "0009ERROR NO LINK TO VAL II"

    assert WCPeer.await_status(peer, 40, "GRIPPER_CMD", &(&1 =~ "ERROR")) ==
             "0004ERROR NO LINK TO DAQ #1"
  end

  test "a command not in the set ends ERROR UNKNOWN COMMAND", %{peer: peer} do
    WCPeer.send_string(peer, 2, [{"V", 7, "BLOW"}])
    assert ack?(WCPeer.recv_line(peer), 2)

    assert WCPeer.await_status(peer, 3, "VACUUM_CMD", &(&1 =~ "ERROR")) ==
             "0007ERROR UNKNOWN COMMAND BLOW"
  end

  test "rule 1: a repeated set letter runs nothing and both commands answer ERROR", %{
    peer: peer,
    ws: ws
  } do
    WCPeer.send_string(peer, 10, [{"V", 1, "ON"}, {"V", 2, "OFF"}])
    assert ack?(WCPeer.recv_line(peer), 10)
    assert WCPeer.status(peer, 11, 1, "VACUUM_CMD") == "0002ERROR RULE 1 SET V REPEATED"
    assert Mailbox.in_flight(ws, :vacuum) == nil
    assert Mailbox.cmd_in(ws, :vacuum) == {nil, nil}
  end

  test "rule 2: a status command with other commands runs nothing", %{peer: peer, ws: ws} do
    WCPeer.send_string(peer, 12, [{"G", 5, "OPEN"}, {"S", 40, "GRIPPER_CMD"}])
    assert ack?(WCPeer.recv_line(peer), 12)

    assert WCPeer.status(peer, 13, 41, "GRIPPER_CMD") ==
             "0005ERROR RULE 2 STATUS COMMAND NOT ALONE"

    assert Mailbox.cmd_in(ws, :gripper) == {nil, nil}
  end

  test "an unknown command-set letter runs nothing", %{peer: peer, ws: ws} do
    WCPeer.send_string(peer, 14, [{"G", 6, "OPEN"}, {"X", 1, "FLY"}])
    assert ack?(WCPeer.recv_line(peer), 14)
    assert WCPeer.status(peer, 15, 1, "GRIPPER_CMD") == "0006ERROR UNKNOWN COMMAND SET X"
    assert Mailbox.cmd_in(ws, :gripper) == {nil, nil}
  end

  @tag :held
  test "rule 3: a command for a busy set answers ERROR BUSY and does not run", %{
    peer: peer,
    ws: ws
  } do
    WCPeer.send_string(peer, 20, [{"R", 9, "HOLD A"}])
    assert ack?(WCPeer.recv_line(peer), 20)
    assert_receive {:executing, runner, 9, {:hold, "HOLD A"}}, 5_000

    # status is answered at once while the partition is busy
    assert WCPeer.status(peer, 21, 39, "ROBOT_CMD") == "0009EXECUTING"

    WCPeer.send_string(peer, 22, [{"R", 10, "HOLD B"}])
    assert ack?(WCPeer.recv_line(peer), 22)
    assert WCPeer.status(peer, 23, 39, "ROBOT_CMD") == "0010ERROR BUSY 0009"
    refute_receive {:executing, _, 10, _}, 100

    send(runner, {:result, :done})
    assert eventually(fn -> Mailbox.in_flight(ws, :robot) == nil end)

    WCPeer.send_string(peer, 24, [{"R", 11, "HOLD C"}])
    assert ack?(WCPeer.recv_line(peer), 24)
    assert_receive {:executing, runner, 11, _}, 5_000
    send(runner, {:result, {:error, "TEST FAILURE"}})

    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ "ERROR")) ==
             "0011ERROR TEST FAILURE"
  end

  test "a Monarch command is parsed once, by MONARCH: SUN_COMM only recognises the transfers",
       %{peer: peer, ws: ws} do
    sun_comm = Vws.CEC.Workstation.whereis(ws, :sun_comm)
    monarch = Vws.CEC.Partition.whereis(ws, :monarch)
    # a pattern set before its module is loaded is lost
    Code.ensure_loaded!(Vws.Codecs.Commands)
    :erlang.trace_pattern({Vws.Codecs.Commands, :parse, 2}, true, [:local])
    :erlang.trace(sun_comm, true, [:call])
    # MONARCH parses in the process it runs each command in
    :erlang.trace(monarch, true, [:call, :set_on_spawn])

    try do
      WCPeer.send_string(peer, 70, [{"M", 3, "TABLE(1/2/3)"}])
      assert ack?(WCPeer.recv_line(peer), 70)

      assert WCPeer.await_status(peer, 35, "MONARCH_CMD", &(&1 =~ "ERROR")) ==
               "0003ERROR NO LINK TO GE-2000"
    after
      :erlang.trace(sun_comm, false, [:call])
      :erlang.trace(monarch, false, [:call, :set_on_spawn])
      :erlang.trace_pattern({Vws.Codecs.Commands, :parse, 2}, false, [:local])
    end

    parses =
      Stream.repeatedly(fn ->
        receive do
          {:trace, pid, :call, {Vws.Codecs.Commands, :parse, [:monarch, text]}} -> {pid, text}
        after
          0 -> nil
        end
      end)
      |> Enum.take_while(& &1)

    assert [{pid, "TABLE(1/2/3)"}] = parses
    assert pid != sun_comm
  end

  @tag :held
  test "rule 4: a retransmitted string is acknowledged again and not executed twice", %{
    peer: peer
  } do
    line = WCPeer.send_string(peer, 30, [{"R", 12, "HOLD"}])
    assert ack?(WCPeer.recv_line(peer), 30)
    assert_receive {:executing, runner, 12, _}, 5_000
    send(runner, {:result, :done})
    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 == "0012DONE")) == "0012DONE"

    # the acknowledgement was lost: the WC sends the same string again
    WCPeer.send_raw(peer, line)
    assert ack?(WCPeer.recv_line(peer), 30)
    refute_receive {:executing, _, _, _}, 200
    assert WCPeer.status(peer, 31, 39, "ROBOT_CMD") == "0012DONE"
  end

  @tag :held
  test "rule 4: the last sequence number with other bytes is a new string from a restarted WC",
       %{peer: peer} do
    WCPeer.send_string(peer, 1, [{"R", 13, "HOLD"}])
    assert ack?(WCPeer.recv_line(peer), 1)
    assert_receive {:executing, runner, 13, _}, 5_000
    send(runner, {:result, :done})
    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 == "0013DONE")) == "0013DONE"

    # the WC restarted and numbers from 1 again: its first string is acknowledged once and run
    WCPeer.send_string(peer, 1, [{"R", 1, "HOLD"}])
    assert ack?(WCPeer.recv_line(peer), 1)
    assert_receive {:executing, runner, 1, _}, 5_000
    send(runner, {:result, :done})
    assert WCPeer.await_status(peer, 40, "ROBOT_CMD", &(&1 == "0001DONE")) == "0001DONE"
  end

  test "an empty line is answered E at once", %{peer: peer} do
    WCPeer.send_raw(peer, "\r\n")
    assert WCPeer.recv_line(peer) == "E"
    assert WCPeer.status(peer, 44, 1, "ROBOT_CMD") == "0000NONE"
  end

  test "a command of an unknown set breaks a rule; its error is asked as <letter>_CMD", %{
    peer: peer
  } do
    WCPeer.send_string(peer, 45, [{"Q", 5, "FROB"}, {"V", 2, "ON"}])
    assert ack?(WCPeer.recv_line(peer), 45)
    assert WCPeer.status(peer, 46, 1, "Q_CMD") == "0005ERROR UNKNOWN COMMAND SET Q"
    assert WCPeer.status(peer, 47, 2, "VACUUM_CMD") == "0002ERROR UNKNOWN COMMAND SET Q"
    assert WCPeer.status(peer, 48, 3, "X_CMD") == "0000NONE"
    assert WCPeer.status(peer, 49, 4, "G_CMD") == "ERROR UNKNOWN STATUS G_CMD"
  end

  test "device status answers say truthfully that no data has come in", %{peer: peer} do
    assert WCPeer.status(peer, 40, 1, "VISE") == "NO DATA (NO LINK TO DAQ #1)"
    assert WCPeer.status(peer, 41, 2, "WHERE_ROBOT") == "NO DATA (NO LINK TO VAL II)"
    assert WCPeer.status(peer, 42, 3, "NONSENSE") == "ERROR UNKNOWN STATUS NONSENSE"
  end

  test "an overlong line is answered E at once, before its LF, and the link goes on", %{
    peer: peer
  } do
    WCPeer.send_raw(peer, String.duplicate("X", 1025))
    assert WCPeer.recv_line(peer) == "E"
    WCPeer.send_line(peer, String.duplicate("X", 5000))
    assert WCPeer.status(peer, 43, 1, "ROBOT_CMD") == "0000NONE"
  end

  describe "NC program transfers" do
    test "DOWNLOAD_HP stores the program; UPLOAD_SUN of an empty NC_UP ends ERROR", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 50, [{"M", 1, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 50)

      program = ["%", "O001234", "N10 G90 G00 X0 Y0", "N20 M30", "%"]

      for {line, n} <- Enum.with_index(program, 1) do
        WCPeer.send_raw(peer, nc(n, line))
        assert WCPeer.recv_line(peer) == answer(program, n)
      end

      assert answer(program, 5) == "A0005/52D5021"
      assert WCPeer.status(peer, 51, 35, "MONARCH_CMD") == "0001DONE"
      assert Mailbox.nc_file(ws) == program

      WCPeer.send_string(peer, 52, [{"M", 2, "UPLOAD_SUN"}])
      assert ack?(WCPeer.recv_line(peer), 52)
      assert WCPeer.status(peer, 53, 35, "MONARCH_CMD") == "0002ERROR NO UPLOADED PROGRAM"
    end

    test "DOWNLOAD_HP(cccc) with the program's CRC: stored, DONE; the closing answer names the CRC",
         %{peer: peer, ws: ws} do
      program = ["%", "O001234", "N10 G90 G00 X0 Y0", "N20 M30", "%"]
      WCPeer.send_string(peer, 90, [{"M", 20, "DOWNLOAD_HP(52D5)"}])
      assert ack?(WCPeer.recv_line(peer), 90)

      for {line, n} <- Enum.with_index(program, 1) do
        WCPeer.send_raw(peer, nc(n, line))
        assert WCPeer.recv_line(peer) == answer(program, n)
      end

      assert WCPeer.status(peer, 91, 35, "MONARCH_CMD") == "0020DONE"
      assert Mailbox.nc_file(ws) == program
    end

    test "DOWNLOAD_HP(cccc) with another CRC than what came: ERROR PROGRAM CRC, the NC file kept",
         %{peer: peer, ws: ws} do
      old = ["%", "O000001", "N10 M30", "%"]
      :ok = Mailbox.put_nc_file(ws, old)
      # what the WC sent: N10 G90 …; what arrived: two bits of line 3 flipped, its 8-bit sum
      # (the BCC) the same — 'G' 0x47 → 'F' 0x46 and '0' 0x30 → '1' 0x31
      sent = ["%", "O001234", "N10 G90 G00 X0 Y0", "N20 M30", "%"]
      arrived = ["%", "O001234", "N10 F90 G01 X0 Y0", "N20 M30", "%"]

      assert Vws.Codecs.WC.BCC.compute("0003" <> Enum.at(sent, 2)) ==
               Vws.Codecs.WC.BCC.compute("0003" <> Enum.at(arrived, 2))

      got = ProgramCRC.format(ProgramCRC.compute(arrived))
      WCPeer.send_string(peer, 92, [{"M", 21, "DOWNLOAD_HP(52D5)"}])
      assert ack?(WCPeer.recv_line(peer), 92)

      for {line, n} <- Enum.with_index(arrived, 1) do
        WCPeer.send_raw(peer, nc(n, line))
        # every line stored as it came; the closing one answered with the CRC of what came
        assert WCPeer.recv_line(peer) == answer(arrived, n)
      end

      # the closing line again (its answer lost): the same answer, nothing stored
      WCPeer.send_raw(peer, nc(5, "%"))
      assert WCPeer.recv_line(peer) == answer(arrived, 5)

      assert WCPeer.status(peer, 93, 35, "MONARCH_CMD") ==
               "0021ERROR PROGRAM CRC #{got} EXPECTED 52D5"

      assert Mailbox.nc_file(ws) == old
    end

    test "DOWNLOAD_HP with a CRC that is not four hex digits: the lines are read, ERROR, nothing stored",
         %{peer: peer, ws: ws} do
      program = ["%", "O000002", "%"]
      WCPeer.send_string(peer, 94, [{"M", 22, "DOWNLOAD_HP(52D)"}])
      assert ack?(WCPeer.recv_line(peer), 94)

      for {line, n} <- Enum.with_index(program, 1) do
        WCPeer.send_raw(peer, nc(n, line))
        assert WCPeer.recv_line(peer) == answer(program, n)
      end

      assert WCPeer.status(peer, 95, 35, "MONARCH_CMD") == "0022ERROR BAD PROGRAM CRC 52D"
      assert Mailbox.nc_file(ws) == []
    end

    test "a program over 999,999 bytes ends ERROR PROGRAM TOO LARGE and is not stored; " <>
           "one of 999,999 is stored",
         %{peer: peer, ws: ws} do
      old = ["%", "O000001", "N10 M30", "%"]
      :ok = Mailbox.put_nc_file(ws, old)
      # "%", a line of 994 + `extra` bytes, 999 lines of 999, "%" — each with its LF: a text of
      # exactly 999,999 + `extra` bytes
      program = fn extra ->
        body = for i <- 1..999, do: String.pad_trailing("N#{i} G01 X", 999, "0")
        ["%", "O000003 " <> String.duplicate("X", 994 + extra - 8)] ++ body ++ ["%"]
      end

      download = fn lines, seq, number ->
        crc = ProgramCRC.format(ProgramCRC.compute(lines))
        WCPeer.send_string(peer, seq, [{"M", number, "DOWNLOAD_HP(#{crc})"}])
        assert ack?(WCPeer.recv_line(peer), seq)

        for {line, n} <- Enum.with_index(lines, 1) do
          WCPeer.send_raw(peer, nc(n, line))
          assert WCPeer.recv_line(peer) == answer(lines, n)
        end

        WCPeer.status(peer, seq + 1, 35, "MONARCH_CMD")
      end

      big = program.(1)
      assert byte_size(Vws.Links.DNC.Program.to_text(big)) == 1_000_000

      assert download.(big, 96, 23) ==
               "0023ERROR PROGRAM TOO LARGE 1000000 BYTES (LIMIT 999999)"

      assert Mailbox.nc_file(ws) == old

      limit = program.(0)
      assert byte_size(Vws.Links.DNC.Program.to_text(limit)) == 999_999
      assert download.(limit, 98, 24) == "0024DONE"
      assert Mailbox.nc_file(ws) == limit
    end

    test "a program line with a bad BCC is answered E and can be sent again", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 60, [{"M", 3, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 60)
      WCPeer.send_raw(peer, nc(1, "%"))
      assert WCPeer.recv_line(peer) == stored(1)
      WCPeer.send_line(peer, "0002N10 G00X0000")
      assert WCPeer.recv_line(peer) == "E"
      WCPeer.send_raw(peer, nc(2, "N10 G00X0"))
      assert WCPeer.recv_line(peer) == stored(2)
      # our answer reached the WC damaged: it sends line 2 again, which is not stored twice
      WCPeer.send_raw(peer, nc(2, "N10 G00X0"))
      assert WCPeer.recv_line(peer) == stored(2)
      WCPeer.send_raw(peer, nc(3, "%"))
      assert WCPeer.recv_line(peer) == answer(["%", "N10 G00X0", "%"], 3)
      # and the closing line's answer too: answered again after the command ended
      WCPeer.send_raw(peer, nc(3, "%"))
      assert WCPeer.recv_line(peer) == answer(["%", "N10 G00X0", "%"], 3)
      assert WCPeer.status(peer, 61, 35, "MONARCH_CMD") == "0003DONE"
      assert Mailbox.nc_file(ws) == ["%", "N10 G00X0", "%"]
    end

    test "a line number that is neither the next nor the last ends ERROR OUT OF ORDER", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 58, [{"M", 10, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 58)
      WCPeer.send_raw(peer, nc(1, "%"))
      assert WCPeer.recv_line(peer) == stored(1)
      WCPeer.send_raw(peer, nc(3, "N10 G00X0"))
      assert WCPeer.recv_line(peer) == "E"
      assert WCPeer.status(peer, 59, 35, "MONARCH_CMD") == "0010ERROR PROGRAM LINE OUT OF ORDER"
      assert Mailbox.nc_file(ws) == []
    end

    test "a program line whose end never comes is dropped after a silence and answered E", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 62, [{"M", 6, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 62)
      WCPeer.send_raw(peer, nc(1, "%"))
      assert WCPeer.recv_line(peer) == stored(1)
      # the line's LF damaged on the wire: SUN_COMM holds an unfinished line, the WC waits
      [line, _crlf] = nc(2, "N10 G00X0") |> IO.iodata_to_binary() |> String.split("\r")

      WCPeer.send_raw(peer, line <> "\r\x1A")
      t0 = System.monotonic_time(:millisecond)
      assert WCPeer.recv_line(peer, 5_000) == "E"
      # not before the inter-character silence (500 ms by default)
      assert System.monotonic_time(:millisecond) - t0 >= 400
      # the WC sends the line again; stored once
      WCPeer.send_raw(peer, nc(2, "N10 G00X0"))
      assert WCPeer.recv_line(peer) == stored(2)
      WCPeer.send_raw(peer, nc(3, "%"))
      assert WCPeer.recv_line(peer) == answer(["%", "N10 G00X0", "%"], 3)
      assert WCPeer.status(peer, 63, 35, "MONARCH_CMD") == "0006DONE"
      assert Mailbox.nc_file(ws) == ["%", "N10 G00X0", "%"]
    end

    test "DOWNLOAD_HP whose acknowledgement was lost: the string again is acknowledged again",
         %{peer: peer, ws: ws} do
      line = WCPeer.send_string(peer, 64, [{"M", 7, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 64)
      # the 05A never reached the WC, which sends the string again: SUN_COMM is reading
      # program lines by now, and must not take the string for one
      WCPeer.send_raw(peer, line)
      assert ack?(WCPeer.recv_line(peer), 64)

      for {text, n} <- Enum.with_index(["%", "N10 G00X0", "%"], 1) do
        WCPeer.send_raw(peer, nc(n, text))
        assert WCPeer.recv_line(peer) == answer(["%", "N10 G00X0", "%"], n)
      end

      assert WCPeer.status(peer, 65, 35, "MONARCH_CMD") == "0007DONE"
      assert Mailbox.nc_file(ws) == ["%", "N10 G00X0", "%"]
    end

    test "another command string during a download: the WC left it; it ends ERROR", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 66, [{"M", 8, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 66)
      WCPeer.send_raw(peer, nc(1, "%"))
      assert WCPeer.recv_line(peer) == stored(1)

      # the WC gave the transfer up: its next string is a string, answered as one
      assert WCPeer.status(peer, 67, 35, "MONARCH_CMD") ==
               "0008ERROR COMMAND STRING FROM THE WC DURING DOWNLOAD AFTER 1 LINES"

      assert Mailbox.nc_file(ws) == []
      WCPeer.send_string(peer, 68, [{"V", 1, "ON"}])
      assert ack?(WCPeer.recv_line(peer), 68)
    end

    test "a string that ends a download is decoded once and handled decoded", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 66, [{"M", 8, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 66)

      # count SUN_COMM's calls of the string decoder while it handles the string that ends
      # the transfer (it decoded that string twice: to see that it is one, and again to run it)
      sun_comm = Vws.CEC.Workstation.whereis(ws, :sun_comm)
      Code.ensure_loaded!(Vws.Codecs.WC.CommandString)
      :erlang.trace_pattern({Vws.Codecs.WC.CommandString, :decode, 2}, true, [:local])
      :erlang.trace(sun_comm, true, [:call])

      try do
        WCPeer.send_string(peer, 67, [{"V", 1, "ON"}])
        assert ack?(WCPeer.recv_line(peer), 67)
      after
        :erlang.trace(sun_comm, false, [:call])
        :erlang.trace_pattern({Vws.Codecs.WC.CommandString, :decode, 2}, false, [:local])
      end

      decodes =
        Stream.repeatedly(fn ->
          receive do
            {:trace, ^sun_comm, :call, {Vws.Codecs.WC.CommandString, :decode, [line, _]}} -> line
          after
            0 -> nil
          end
        end)
        |> Enum.take_while(& &1)

      assert [line] = decodes
      assert line =~ ~r/^\*0067\*V0001ON\*/

      assert WCPeer.status(peer, 68, 35, "MONARCH_CMD") ==
               "0008ERROR COMMAND STRING FROM THE WC DURING DOWNLOAD AFTER 0 LINES"
    end

    test "UPLOAD_SUN whose acknowledgement was lost: acknowledged again, sent from line 1", %{
      peer: peer,
      ws: ws
    } do
      program = ["%", "O000777", "%"]
      Mailbox.put_nc_up(ws, program)
      line = WCPeer.send_string(peer, 72, [{"M", 9, "UPLOAD_SUN"}])
      assert ack?(WCPeer.recv_line(peer), 72)
      first = WCPeer.recv_line(peer)
      assert {:ok, {:line, 1, "%"}} = Vws.Codecs.WC.Reply.decode_line(first)
      # the WC saw neither: it sends the string again
      WCPeer.send_raw(peer, line)
      assert ack?(WCPeer.recv_line(peer), 72)

      received =
        for n <- 1..length(program) do
          l = WCPeer.recv_line(peer)
          WCPeer.send_raw(peer, Vws.Codecs.WC.Reply.encode({:line_ack, n}))
          {:ok, {:line, ^n, text}} = Vws.Codecs.WC.Reply.decode_line(l)
          text
        end

      assert received == List.replace_at(program, -1, closing(program))
      assert WCPeer.status(peer, 73, 35, "MONARCH_CMD") == "0009DONE"
    end

    test "UPLOAD_SUN sends NC_UP line by line and resends a line answered E", %{
      peer: peer,
      ws: ws
    } do
      program = ["%", "O000777", "N10 G01 X1.0", "%"]
      Mailbox.put_nc_up(ws, program)
      WCPeer.send_string(peer, 70, [{"M", 4, "UPLOAD_SUN"}])
      assert ack?(WCPeer.recv_line(peer), 70)
      # the closing line carries the program's CRC (PROTOCOLS.md §1 "Whole-program check")
      sent = List.replace_at(program, -1, closing(program))
      assert List.last(sent) == "%/084C"

      received =
        for {expected, n} <- Enum.with_index(sent, 1) do
          line = WCPeer.recv_line(peer)

          case n do
            2 ->
              # ask for this line again once
              WCPeer.send_line(peer, "E")
              assert WCPeer.recv_line(peer) == line

            3 ->
              # a damaged answer (one bit) is no answer: the line comes again
              WCPeer.send_line(peer, "A0003005")
              assert WCPeer.recv_line(peer) == line

            _ ->
              :ok
          end

          WCPeer.send_raw(peer, Vws.Codecs.WC.Reply.encode({:line_ack, n}))
          assert {:ok, {:line, ^n, ^expected}} = Vws.Codecs.WC.Reply.decode_line(line)
          expected
        end

      assert received == sent
      assert WCPeer.status(peer, 71, 35, "MONARCH_CMD") == "0004DONE"
    end

    test "a status query while the answer to the closing line is outstanding: answered, the upload goes on",
         %{peer: peer, ws: ws} do
      Mailbox.put_nc_up(ws, ["%", "O000777", "%"])
      WCPeer.send_string(peer, 74, [{"M", 11, "UPLOAD_SUN"}])
      assert ack?(WCPeer.recv_line(peer), 74)

      for n <- 1..2 do
        assert {:ok, {:line, ^n, _}} = Vws.Codecs.WC.Reply.decode_line(WCPeer.recv_line(peer))
        WCPeer.send_raw(peer, Vws.Codecs.WC.Reply.encode({:line_ack, n}))
      end

      closing = WCPeer.recv_line(peer)
      text = closing(["%", "O000777", "%"])
      assert {:ok, {:line, 3, ^text}} = Vws.Codecs.WC.Reply.decode_line(closing)
      # the WC has the program; its answer arrives damaged and it asks the command's status
      WCPeer.send_line(peer, "A0003005")
      assert WCPeer.recv_line(peer) == closing
      assert WCPeer.status(peer, 75, 35, "MONARCH_CMD") == "0011EXECUTING"
      WCPeer.send_raw(peer, Vws.Codecs.WC.Reply.encode({:line_ack, 3}))
      assert WCPeer.await_status(peer, 76, "MONARCH_CMD", &(&1 =~ "DONE")) == "0011DONE"
    end

    test "a download that loses its link ends the Monarch command ERROR", %{
      peer: peer,
      ws: ws,
      wc: wc
    } do
      WCPeer.send_string(peer, 80, [{"M", 5, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 80)
      WCPeer.send_raw(peer, nc(1, "%"))
      assert WCPeer.recv_line(peer) == stored(1)
      WCPeer.close(peer)
      assert eventually(fn -> match?({5, {:error, _}}, Mailbox.command_status(ws, :monarch)) end)
      {:ok, peer2} = WCPeer.connect(wc)

      assert WCPeer.status(peer2, 81, 35, "MONARCH_CMD") =~
               ~r/^0005ERROR WC LINK LOST DURING DOWNLOAD/
    end
  end

  @tag takeover_after: 0
  test "with takeover_after 0, a new WC connection takes over from the previous one, which is closed",
       %{
         peer: peer,
         wc: wc,
         ws: ws
       } do
    {:ok, peer2} = WCPeer.connect(wc)
    assert WCPeer.status(peer2, 90, 1, "ROBOT_CMD") == "0000NONE"
    assert WCPeer.recv_line(peer, 200) == {:timeout, :closed}
    assert Vws.CEC.SunComm.info(ws).counters.connections == 2
  end

  test "by default a new WC connection is refused while the current one has been heard within 10 s",
       %{peer: peer, wc: wc, ws: ws} do
    assert WCPeer.status(peer, 90, 1, "ROBOT_CMD") == "0000NONE"
    {:ok, peer2} = WCPeer.connect(wc)
    # closed unanswered once its grace (500 ms) for the current WC's close has run out
    assert WCPeer.recv_line(peer2, 2_000) in [{:timeout, :closed}, :closed]
    assert WCPeer.status(peer, 91, 1, "ROBOT_CMD") == "0000NONE"
    assert Vws.CEC.SunComm.info(ws).counters.connections == 1
  end

  test "SUN_COMM takes no WC string before OK_TO_PROCEED" do
    ws = "before-ok-#{System.unique_integer([:positive])}"
    start_supervised!({Vws.CEC.Mailbox.Owner, workstation: ws})
    start_supervised!({Vws.CEC.SunComm, workstation: ws, wc: "loopback:wc-#{ws}"})
    assert {:error, _} = Vws.Links.Transport.connect("loopback:wc-#{ws}")
    assert Vws.CEC.SunComm.info(ws).listening == nil
    assert Vws.CEC.SunComm.await_listening(ws, 50) == nil

    # await_listening/2 is woken by the :wc_listening event SUN_COMM causes as it opens
    waiter = Task.async(fn -> Vws.CEC.SunComm.await_listening(ws, 30_000) end)
    :ok = Events.cause(ws, :ok_to_proceed)
    assert %Vws.Links.Endpoint{} = listening = Task.await(waiter, 30_000)
    assert to_string(listening) =~ "loopback:wc-#{ws}"
    {:ok, peer} = WCPeer.connect("loopback:wc-#{ws}")
    assert WCPeer.status(peer, 1, 1, "GRIPPER_CMD") == "0000NONE"
  end
end
