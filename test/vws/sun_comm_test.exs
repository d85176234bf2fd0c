defmodule Vws.SunCommTest do
  use ExUnit.Case, async: true

  alias Vws.{Mailbox, Events}
  alias Vws.Test.{WCPeer, Workstation}
  import Vws.Test.Eventually

  defp ack?(line, seq), do: Vws.WC.Reply.decode(line) == {:ok, {:ack, seq}}

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
  test "rule 4: the last sequence number with other bytes is refused E and runs nothing", %{
    peer: peer
  } do
    WCPeer.send_string(peer, 32, [{"R", 13, "HOLD"}])
    assert ack?(WCPeer.recv_line(peer), 32)
    assert_receive {:executing, runner, 13, _}, 5_000
    send(runner, {:result, :done})
    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 == "0013DONE")) == "0013DONE"

    # "O"->"N" and "*"->"+" in one resend: the 8-bit sum cannot see it
    WCPeer.send_string(peer, 32, [{"R", 13, "HOLD"}, {"G", 1, "OPEN"}])
    assert WCPeer.recv_line(peer) == "E"
    refute_receive {:executing, _, _, _}, 200
  end

  test "device status answers say truthfully that no data has come in", %{peer: peer} do
    assert WCPeer.status(peer, 40, 1, "VISE") == "NO DATA (NO LINK TO DAQ #1)"
    assert WCPeer.status(peer, 41, 2, "WHERE_ROBOT") == "NO DATA (NO LINK TO VAL II)"
    assert WCPeer.status(peer, 42, 3, "NONSENSE") == "ERROR UNKNOWN STATUS NONSENSE"
  end

  test "an overlong line is answered E and the link goes on", %{peer: peer} do
    WCPeer.send_line(peer, String.duplicate("X", 5000))
    assert WCPeer.recv_line(peer) == "E"
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

      for line <- program do
        WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, line}))
        assert WCPeer.recv_line(peer) == "A"
      end

      assert WCPeer.status(peer, 51, 35, "MONARCH_CMD") == "0001DONE"
      assert Mailbox.nc_file(ws) == program

      WCPeer.send_string(peer, 52, [{"M", 2, "UPLOAD_SUN"}])
      assert ack?(WCPeer.recv_line(peer), 52)
      assert WCPeer.status(peer, 53, 35, "MONARCH_CMD") == "0002ERROR NO UPLOADED PROGRAM"
    end

    test "a program line with a bad BCC is answered E and can be sent again", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 60, [{"M", 3, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 60)
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "%"}))
      assert WCPeer.recv_line(peer) == "A"
      WCPeer.send_line(peer, "N10 G00X0000")
      assert WCPeer.recv_line(peer) == "E"
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "N10 G00X0"}))
      assert WCPeer.recv_line(peer) == "A"
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "%"}))
      assert WCPeer.recv_line(peer) == "A"
      assert WCPeer.status(peer, 61, 35, "MONARCH_CMD") == "0003DONE"
      assert Mailbox.nc_file(ws) == ["%", "N10 G00X0", "%"]
    end

    test "a program line whose end never comes is dropped after a silence and answered E", %{
      peer: peer,
      ws: ws
    } do
      WCPeer.send_string(peer, 62, [{"M", 6, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 62)
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "%"}))
      assert WCPeer.recv_line(peer) == "A"
      # the line's LF damaged on the wire: SUN_COMM holds an unfinished line, the WC waits
      [line, _crlf] =
        Vws.WC.Reply.encode({:line, "N10 G00X0"}) |> IO.iodata_to_binary() |> String.split("\r")

      WCPeer.send_raw(peer, line <> "\r\x1A")
      t0 = System.monotonic_time(:millisecond)
      assert WCPeer.recv_line(peer, 5_000) == "E"
      # not before the inter-character silence (500 ms by default)
      assert System.monotonic_time(:millisecond) - t0 >= 400
      # the WC sends the line again; stored once
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "N10 G00X0"}))
      assert WCPeer.recv_line(peer) == "A"
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "%"}))
      assert WCPeer.recv_line(peer) == "A"
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

      for text <- ["%", "N10 G00X0", "%"] do
        WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, text}))
        assert WCPeer.recv_line(peer) == "A"
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
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "%"}))
      assert WCPeer.recv_line(peer) == "A"

      # the WC gave the transfer up: its next string is a string, answered as one
      assert WCPeer.status(peer, 67, 35, "MONARCH_CMD") ==
               "0008ERROR COMMAND STRING FROM THE WC DURING DOWNLOAD AFTER 1 LINES"

      assert Mailbox.nc_file(ws) == []
      WCPeer.send_string(peer, 68, [{"V", 1, "ON"}])
      assert ack?(WCPeer.recv_line(peer), 68)
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
      assert {:ok, {:line, "%"}} = Vws.WC.Reply.decode_line(first)
      # the WC saw neither: it sends the string again
      WCPeer.send_raw(peer, line)
      assert ack?(WCPeer.recv_line(peer), 72)

      received =
        for _ <- program do
          l = WCPeer.recv_line(peer)
          WCPeer.send_line(peer, "A")
          {:ok, {:line, text}} = Vws.WC.Reply.decode_line(l)
          text
        end

      assert received == program
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

      received =
        for {expected, i} <- Enum.with_index(program) do
          line = WCPeer.recv_line(peer)

          if i == 1 do
            # ask for this line again once
            WCPeer.send_line(peer, "E")
            assert WCPeer.recv_line(peer) == line
          end

          WCPeer.send_line(peer, "A")
          assert {:ok, {:line, ^expected}} = Vws.WC.Reply.decode_line(line)
          expected
        end

      assert received == program
      assert WCPeer.status(peer, 71, 35, "MONARCH_CMD") == "0004DONE"
    end

    test "a download that loses its link ends the Monarch command ERROR", %{
      peer: peer,
      ws: ws,
      wc: wc
    } do
      WCPeer.send_string(peer, 80, [{"M", 5, "DOWNLOAD_HP"}])
      assert ack?(WCPeer.recv_line(peer), 80)
      WCPeer.send_raw(peer, Vws.WC.Reply.encode({:line, "%"}))
      assert WCPeer.recv_line(peer) == "A"
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
    assert Vws.SunComm.info(ws).counters.connections == 2
  end

  test "by default a new WC connection is refused while the current one has been heard within 10 s",
       %{peer: peer, wc: wc, ws: ws} do
    assert WCPeer.status(peer, 90, 1, "ROBOT_CMD") == "0000NONE"
    {:ok, peer2} = WCPeer.connect(wc)
    assert WCPeer.recv_line(peer2, 200) == {:timeout, :closed}
    assert WCPeer.status(peer, 91, 1, "ROBOT_CMD") == "0000NONE"
    assert Vws.SunComm.info(ws).counters.connections == 1
  end

  test "SUN_COMM takes no WC string before OK_TO_PROCEED" do
    ws = "before-ok-#{System.unique_integer([:positive])}"
    start_supervised!({Vws.Mailbox.Owner, workstation: ws})
    start_supervised!({Vws.SunComm, workstation: ws, wc: "loopback:wc-#{ws}"})
    assert {:error, _} = Vws.Transport.connect("loopback:wc-#{ws}")
    assert Vws.SunComm.info(ws).listening == nil

    :ok = Events.cause(ws, :ok_to_proceed)
    {:ok, peer} = WCPeer.connect("loopback:wc-#{ws}")
    assert WCPeer.status(peer, 1, 1, "GRIPPER_CMD") == "0000NONE"
  end
end
