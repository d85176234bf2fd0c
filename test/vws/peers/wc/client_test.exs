defmodule Vws.Codecs.WC.ClientTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, SunComm}
  alias Vws.Peers.WC.{Client, ClientError}
  alias Vws.Peers.WC.Client.Event
  alias Vws.Test.{LineRelay, ObedientPartition, WCPeer, Workstation}
  import Vws.Test.Eventually

  doctest Vws.Peers.WC.Client
  doctest Vws.Peers.WC.ClientError

  defp sent(client), do: for(%Event{direction: :sent, line: l} <- Client.log(client), do: l)

  defp received(client),
    do: for(%Event{direction: :received, line: l} <- Client.log(client), do: l)

  # A wire line (`nnnn` + text + BBB) with two bits of its text flipped so that its 8-bit sum,
  # the BCC, stays the same: bit 0 set in one byte and cleared in another (printable both).
  defp sum_keeping_flip(line) do
    size = byte_size(line) - 3
    <<body::binary-size(size), bcc::binary>> = line
    <<number::binary-4, text::binary>> = body
    bytes = :binary.bin_to_list(text)
    indexed = Enum.with_index(bytes)
    {_, one} = Enum.find(indexed, fn {b, _} -> Bitwise.band(b, 1) == 1 end)
    {_, zero} = Enum.find(indexed, fn {b, _} -> Bitwise.band(b, 1) == 0 and b != ?~ end)

    flipped =
      bytes
      |> List.update_at(one, &Bitwise.bxor(&1, 1))
      |> List.update_at(zero, &Bitwise.bxor(&1, 1))

    damaged = number <> :binary.list_to_bin(flipped)
    # the damage the BCC cannot see
    true = Vws.Codecs.WC.BCC.compute(damaged) == Vws.Codecs.WC.BCC.compute(body)
    damaged <> bcc
  end

  defp relay(wc) do
    name = "relay-#{System.unique_integer([:positive])}"
    {:ok, relay} = LineRelay.start_link(wc, name)
    {relay, "loopback:#{name}"}
  end

  describe "seed Table 1" do
    setup do
      %{ws: ws, wc: wc} =
        Workstation.start(partitions: ObedientPartition.partitions(test: self()))

      {:ok, client} = Client.connect(wc, sequence: 54, numbers: %{"R" => 9, "G" => 4, "S" => 39})
      %{ws: ws, client: client}
    end

    test "steps 1-5, string for string and reply for reply", %{ws: ws, client: client} do
      assert {:ok, [{"R", 9}, {"G", 4}]} =
               Client.send_commands(client, [
                 {"R", "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"},
                 {"G", "OPEN"}
               ])

      for n <- [9, 4] do
        assert_receive {:executing, pid, ^n, _}, 5_000
        send(pid, {:result, :done})
      end

      assert eventually(fn -> Mailbox.command_status(ws, :gripper) == {4, :done} end)
      assert eventually(fn -> Mailbox.command_status(ws, :robot) == {9, :done} end)
      assert Client.await_command(client, "R", 9, 5_000) == :done
      assert Client.await_command(client, "G", 4, 5_000) == :done

      assert {:ok, [{"R", 10}]} = Client.send_commands(client, [{"R", "DISABLE_TRAY1"}])
      assert_receive {:executing, pid, 10, "DISABLE_TRAY1"}, 5_000
      send(pid, {:result, :done})
      assert eventually(fn -> Mailbox.command_status(ws, :robot) == {10, :done} end)
      assert Client.await_command(client, "R", 10, 5_000) == :done

      # expected bytes computed with python3 (sum of the bytes mod 256), not with our codec
      assert sent(client) == [
               "*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*241",
               "*0055*S0039ROBOT_CMD*032",
               "*0056*S0040GRIPPER_CMD*172",
               "*0057*R0010DISABLE_TRAY1*033",
               "*0058*S0041ROBOT_CMD*028"
             ]

      assert received(client) == [
               "05A0054111",
               "13S00390009DONE114",
               "13S00400004DONE101",
               "05A0057114",
               "13S00410010DONE099"
             ]

      meanings = for %Event{direction: :received, meaning: m} <- Client.log(client), do: m
      assert Enum.at(meanings, 1) == "ROBOT 0009 DONE"
      assert Enum.at(meanings, 3) == "ack: string 0057 received intact"
    end
  end

  describe "numbering" do
    setup do
      %{ws: ws, wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
      %{ws: ws, wc: wc}
    end

    test "sequence numbers wrap 9999 → 0000, command numbers 9999 → 0001", %{wc: wc} do
      {:ok, client} = Client.connect(wc, sequence: 9999, numbers: %{"V" => 9999})
      assert {:ok, [{"V", 9999}]} = Client.send_commands(client, [{"V", "ON"}])
      assert :done = Client.await_command(client, "V", 9999, 5_000)
      assert {:ok, [{"V", 1}]} = Client.send_commands(client, [{"V", "OFF"}])
      assert ["*9999*V9999ON*" <> _, "*0000*S0001VACUUM_CMD*" <> _ | _] = sent(client)
      assert List.last(sent(client)) =~ ~r/^\*\d{4}\*V0001OFF\*\d{3}$/
    end

    test "each set numbers its own commands; status queries are set S", %{wc: wc} do
      {:ok, client} = Client.connect(wc)
      assert {:ok, [{"R", 1}, {"G", 1}]} = Client.send_commands(client, [{"R", "A"}, {"G", "B"}])
      assert {:ok, _} = Client.status(client, "TRAYS")
      assert {:ok, [{"G", 2}]} = Client.send_commands(client, [{"G", "C"}])

      assert ["*0001*R0001A*G0001B*" <> _, "*0002*S0001TRAYS*" <> _, "*0003*G0002C*" <> _] =
               sent(client)

      assert %{next_sequence: 4, next_numbers: %{"R" => 2, "G" => 3, "S" => 2}} =
               Client.info(client)
    end

    test "requests that could not be sent are refused before any byte goes out", %{wc: wc} do
      {:ok, client} = Client.connect(wc)

      for bad <- [
            [],
            [{"S", "ROBOT_CMD"}],
            [{"R", "A"}, {"R", "B"}],
            [{"G", "OP*EN"}],
            [{"G", ""}]
          ] do
        assert {:error, %ClientError{reason: :bad_request}} = Client.send_commands(client, bad)
      end

      assert {:error, %ClientError{reason: :bad_request}} = Client.download_program(client, ["X"])
      assert sent(client) == []
    end
  end

  describe "the polling rule" do
    setup do
      %{ws: ws, wc: wc} = Workstation.start(partitions: Workstation.held_robot())
      {:ok, client} = Client.connect(wc)
      %{ws: ws, client: client}
    end

    test "EXECUTING is asked again until DONE", %{client: client} do
      {:ok, [{"R", 1}]} = Client.send_commands(client, [{"R", "HOLD"}])
      assert_receive {:executing, runner, 1, _}, 5_000

      waiter =
        Task.async(fn -> Client.await_command(client, "R", 1, 10_000, poll_interval: 5) end)

      assert eventually(fn -> Client.info(client).counters.status_queries >= 3 end)
      send(runner, {:result, :done})
      assert Task.await(waiter) == :done
      meanings = for %Event{kind: :status, meaning: m} <- Client.log(client), do: m
      assert "ROBOT 0001 EXECUTING" in meanings
      assert List.last(meanings) == "ROBOT 0001 DONE"
    end

    test "anything but DONE is the error, with the CEC's reason", %{client: client} do
      {:ok, [{"R", 1}]} = Client.send_commands(client, [{"R", "HOLD"}])
      assert_receive {:executing, runner, 1, _}, 5_000
      send(runner, {:result, {:error, "GRIPPER COLLISION"}})

      assert {:error, %ClientError{reason: :command_failed} = e} =
               Client.await_command(client, "R", 1, 5_000, poll_interval: 5)

      assert Exception.message(e) == "ROBOT command 0001 ended ERROR GRIPPER COLLISION"
    end

    test "a command still executing at the timeout is a timeout", %{client: client} do
      {:ok, [{"R", 1}]} = Client.send_commands(client, [{"R", "HOLD"}])
      assert_receive {:executing, runner, 1, _}, 5_000

      assert {:error, %ClientError{reason: :command_timeout, data: %{last: "0001EXECUTING"}}} =
               Client.await_command(client, "R", 1, 50, poll_interval: 5)

      send(runner, {:result, :done})
    end

    test "a busy set: the refused command's ERROR BUSY stops the WC", %{client: client} do
      {:ok, [{"R", 1}]} = Client.send_commands(client, [{"R", "HOLD"}])
      assert_receive {:executing, runner, 1, _}, 5_000
      # breaking the rule on purpose: a new robot command before DONE
      {:ok, [{"R", 2}]} = Client.send_commands(client, [{"R", "HOLD 2"}])

      assert {:error, %ClientError{data: %{status: "ERROR BUSY 0001"}}} =
               Client.await_command(client, "R", 2, 5_000)

      send(runner, {:result, :done})
    end

    test "the status of a previous command is asked again until the number appears", %{
      client: client
    } do
      # command 1 is the last the CEC knows; the WC awaits 2, which has not reached it yet
      {:ok, [{"R", 1}]} = Client.send_commands(client, [{"R", "HOLD"}])
      assert_receive {:executing, runner, 1, _}, 5_000
      send(runner, {:result, :done})
      assert :done = Client.await_command(client, "R", 1, 5_000)

      asked_before = Client.info(client).counters.status_queries

      waiter =
        Task.async(fn -> Client.await_command(client, "R", 2, 10_000, poll_interval: 5) end)

      # the waiter asks at least four times while the CEC still answers command 1
      assert eventually(fn -> Client.info(client).counters.status_queries >= asked_before + 4 end)
      assert Task.yield(waiter, 0) == nil
      # command 2 goes out while the waiter keeps asking
      assert {:ok, [{"R", 2}]} = Client.send_commands(client, [{"R", "HOLD"}])
      assert_receive {:executing, runner, 2, _}, 5_000
      send(runner, {:result, :done})
      assert Task.await(waiter) == :done

      answers = for %Event{kind: :status, meaning: m} <- Client.log(client), do: m
      assert Enum.count(answers, &(&1 == "ROBOT 0001 DONE")) >= 4
    end
  end

  describe "a bad line on the link" do
    setup do
      %{ws: ws, wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
      {relay, via} = relay(wc)
      %{ws: ws, relay: relay, via: via}
    end

    test "a string answered E is sent again, byte for byte, and runs once", %{
      ws: ws,
      relay: relay,
      via: via
    } do
      {:ok, client} = Client.connect(via)
      :ok = LineRelay.arm(relay, :to_cec, :corrupt)
      assert {:ok, [{"G", 1}]} = Client.send_commands(client, [{"G", "OPEN"}])
      assert :done = Client.await_command(client, "G", 1, 5_000)

      assert [first, again | _] = sent(client)
      assert first == again
      assert ["E", "05A0001" <> _ | _] = received(client)
      assert %{resends: 1, naks: 1} = Client.info(client).counters
      assert SunComm.info(ws).counters.naks == 1
      assert Vws.CEC.Partition.info(ws, :gripper).done == 1
    end

    test "a damaged acknowledgement: the string is sent again, the CEC does not run it twice", %{
      ws: ws,
      relay: relay,
      via: via
    } do
      {:ok, client} = Client.connect(via)
      :ok = LineRelay.arm(relay, :to_wc, :corrupt, &String.starts_with?(&1, "05A"))
      assert {:ok, [{"V", 1}]} = Client.send_commands(client, [{"V", "ON"}])
      assert :done = Client.await_command(client, "V", 1, 5_000)
      assert SunComm.info(ws).counters.retransmissions == 1
      assert Vws.CEC.Partition.info(ws, :vacuum).done == 1

      assert [%Event{kind: :damaged} | _] =
               for(%Event{kind: :damaged} = e <- Client.log(client), do: e)
    end

    test "a string that gets no reply is sent again after the reply timeout", %{
      relay: relay,
      via: via
    } do
      {:ok, client} = Client.connect(via, reply_timeout: 100)
      :ok = LineRelay.arm(relay, :to_cec, :drop)
      assert {:ok, "0000NONE"} = Client.status(client, "GRIPPER_CMD")
      assert %{timeouts: 1, resends: 1} = Client.info(client).counters
    end

    test "resends are bounded", %{relay: relay, via: via} do
      {:ok, client} = Client.connect(via, max_resends: 2, reply_timeout: 100)
      :ok = LineRelay.arm(relay, :to_cec, :corrupt, fn _ -> true end, 3)

      assert {:error, %ClientError{reason: :nak, data: %{sequence: 1, tries: 3}} = e} =
               Client.send_commands(client, [{"G", "OPEN"}])

      assert Exception.message(e) =~ "all 3 tries of string 0001"

      :ok = LineRelay.arm(relay, :to_cec, :drop, fn _ -> true end, 3)

      assert {:error, %ClientError{reason: :timeout, data: %{tries: 3}}} =
               Client.status(client, "TRAYS")

      # the link works again afterwards
      assert {:ok, _} = Client.status(client, "TRAYS")
    end
  end

  describe "NC programs against SUN_COMM" do
    @program ["%", "O001234", "N10 G90 G00 X0 Y0", "N20 G01 Z-1.0 F100", "N30 M30", "%"]

    setup do
      # takeover_after 0: another WC may take the link at once (the default waits for 10 s of
      # silence, see wc_link_policy_test.exs)
      %{ws: ws, wc: wc} = Workstation.start(sun_comm: [takeover_after: 0])
      {relay, via} = relay(wc)
      {:ok, client} = Client.connect(via, line_timeout: 300)
      %{ws: ws, client: client, relay: relay}
    end

    test "DOWNLOAD_HP: every line acknowledged, a damaged one sent again", %{
      ws: ws,
      client: client,
      relay: relay
    } do
      :ok = LineRelay.arm(relay, :to_cec, :corrupt, &(&1 =~ "N20"))
      assert {:ok, {"M", 1}} = Client.download_program(client, @program)
      assert :done = Client.await_command(client, "M", 1, 5_000)
      assert Mailbox.nc_file(ws) == @program

      lines = for %Event{kind: :program_line, line: l} <- Client.log(client), do: l
      assert length(lines) == length(@program) + 1
      assert ["0001%230" | _] = lines
      assert %{lines_sent: 7, resends: 1} = Client.info(client).counters
    end

    test "UPLOAD_SUN: every line received and answered A, a damaged one asked again", %{
      ws: ws,
      client: client,
      relay: relay
    } do
      Mailbox.put_nc_up(ws, @program)
      :ok = LineRelay.arm(relay, :to_wc, :corrupt, &(&1 =~ "N10"))
      assert {:ok, {"M", 1}, @program} = Client.upload_program(client)
      assert :done = Client.await_command(client, "M", 1, 5_000)
      assert %{lines_received: 6, naks_sent: 1} = Client.info(client).counters
    end

    test "DOWNLOAD_HP names the program's CRC; the closing % is answered with the count and it",
         %{ws: ws, client: client} do
      crc = Vws.Codecs.WC.ProgramCRC.compute(@program)
      hex = Vws.Codecs.WC.ProgramCRC.format(crc)
      assert {:ok, {"M", 1}} = Client.download_program(client, @program)
      assert :done = Client.await_command(client, "M", 1, 5_000)
      assert Mailbox.nc_file(ws) == @program
      assert Enum.any?(sent(client), &(&1 =~ "*M0001DOWNLOAD_HP(#{hex})*"))
      assert Enum.any?(received(client), &String.starts_with?(&1, "A0006/#{hex}"))
    end

    test "a program line damaged so that its BCC still holds: the CRC sees it, the CEC keeps " <>
           "its old NC file, the download fails at the client",
         %{ws: ws, client: client, relay: relay} do
      old = ["%", "O000001", "N10 M30", "%"]
      :ok = Mailbox.put_nc_file(ws, old)
      :ok = LineRelay.arm(relay, :to_cec, {:replace, &sum_keeping_flip/1}, &(&1 =~ "N10 G90"))

      assert {:error, %ClientError{reason: :program_crc, data: data} = e} =
               Client.download_program(client, @program)

      assert %{direction: :download, number: 1} = data
      assert data.sent == Vws.Codecs.WC.ProgramCRC.compute(@program)
      assert data.stored != data.sent
      assert Exception.message(e) =~ ~r/^NC program download \(MONARCH command 0001\): the CEC/

      assert {:error, %ClientError{reason: :command_failed, data: %{status: status}}} =
               Client.await_command(client, "M", 1, 5_000)

      assert status =~ ~r/^ERROR PROGRAM CRC [0-9A-F]{4} EXPECTED [0-9A-F]{4}$/
      assert Mailbox.nc_file(ws) == old

      # sent again (the runner does so), it arrives whole
      assert {:ok, {"M", 2}} = Client.download_program(client, @program)
      assert :done = Client.await_command(client, "M", 2, 5_000)
      assert Mailbox.nc_file(ws) == @program
    end

    test "UPLOAD_SUN: a line damaged so that its BCC still holds fails at the client (%/cccc)",
         %{ws: ws, client: client, relay: relay} do
      Mailbox.put_nc_up(ws, @program)
      :ok = LineRelay.arm(relay, :to_wc, {:replace, &sum_keeping_flip/1}, &(&1 =~ "N20 G01"))

      assert {:error, %ClientError{reason: :program_crc, data: data} = e} =
               Client.upload_program(client)

      assert %{direction: :upload, number: 1} = data
      assert data.sent == Vws.Codecs.WC.ProgramCRC.compute(@program)
      assert Exception.message(e) =~ "the program received has CRC"
      closing = "%/" <> Vws.Codecs.WC.ProgramCRC.format(data.sent)
      assert Enum.any?(received(client), &(&1 =~ closing))

      # undamaged, the program comes whole: the closing line is the program's `%` again
      assert {:ok, {"M", 2}, @program} = Client.upload_program(client)
    end

    test "UPLOAD_SUN from a CEC that sends the seed's closing % (no CRC): taken, not compared",
         %{ws: ws, client: client, relay: relay} do
      Mailbox.put_nc_up(ws, @program)

      plain = fn _line ->
        IO.iodata_to_binary(Vws.Codecs.WC.Reply.encode({:line, 6, "%"})) |> String.trim()
      end

      :ok = LineRelay.arm(relay, :to_wc, {:replace, plain}, &String.starts_with?(&1, "0006%/"))
      assert {:ok, {"M", 1}, @program} = Client.upload_program(client)

      assert Enum.any?(Client.log(client), &(&1.meaning =~ "named no CRC"))
    end

    test "UPLOAD_SUN with nothing to send ends with the CEC's reason", %{client: client} do
      assert {:error, %ClientError{reason: :command_failed} = e} = Client.upload_program(client)
      assert Exception.message(e) == "MONARCH command 0001 ended ERROR NO UPLOADED PROGRAM"
    end

    test "a damaged answer to a program line: the line is sent again and stored once", %{
      ws: ws,
      client: client,
      relay: relay
    } do
      # the answer to line 1 damaged: the WC cannot know it was stored and sends it again; the
      # CEC knows the number and answers again without storing it twice
      :ok = LineRelay.arm(relay, :to_wc, :corrupt, &String.starts_with?(&1, "A0001"))

      assert {:ok, {"M", 1}} = Client.download_program(client, @program)
      assert %{transfers_broken: 0, resends: 1} = Client.info(client).counters
      assert :done = Client.await_command(client, "M", 1, 5_000)
      assert Mailbox.nc_file(ws) == @program
    end

    test "a download that breaks off drops the link, so the CEC ends the command ERROR", %{
      client: client,
      relay: relay
    } do
      :ok = LineRelay.arm(relay, :to_cec, :corrupt, &(&1 =~ "N20"), :infinity)

      assert {:error, %ClientError{reason: :transfer_failed, data: %{line: 4}}} =
               Client.download_program(client, @program)

      assert {:error, %ClientError{reason: :command_failed, data: %{status: status}}} =
               Client.await_command(client, "M", 1, 5_000)

      assert status =~ "ERROR WC LINK"
    end
  end

  describe "the link and the event log" do
    setup do
      # takeover_after 0: another WC may take the link at once (the default waits for 10 s of
      # silence, see wc_link_policy_test.exs)
      %{ws: ws, wc: wc} = Workstation.start(sun_comm: [takeover_after: 0])
      %{ws: ws, wc: wc}
    end

    test "subscribers get every line with its time and meaning, and notes in order", %{wc: wc} do
      {:ok, client} = Client.connect(wc, subscribe: self())
      :ok = Client.note(client, "step 1")
      {:ok, "0000NONE"} = Client.status(client, "ROBOT_CMD")

      assert_receive {:wc_client, ^client, %Event{direction: :note, meaning: "step 1"}}

      assert_receive {:wc_client, ^client,
                      %Event{
                        direction: :sent,
                        kind: :status_query,
                        line: "*0001*S0001ROBOT_CMD*" <> _,
                        meaning: "ask ROBOT_CMD"
                      }}

      assert_receive {:wc_client, ^client,
                      %Event{
                        direction: :received,
                        kind: :status,
                        meaning: "ROBOT: no command yet",
                        at: at
                      }}

      assert is_integer(at) and at >= 0
    end

    test "when another WC takes the link over, the next request opens it again", %{wc: wc} do
      {:ok, client} = Client.connect(wc)
      {:ok, _} = Client.status(client, "TRAYS")
      {:ok, peer} = WCPeer.connect(wc)
      assert WCPeer.status(peer, 1, 1, "ROBOT_CMD") == "0000NONE"
      assert eventually(fn -> Client.info(client).peer == nil end)
      assert {:ok, _} = Client.status(client, "TRAYS")
      assert Client.info(client).counters.reconnects == 1
    end

    test "with no CEC to reach, requests answer :closed", %{ws: ws, wc: wc} do
      {:ok, client} = Client.connect(wc)
      :ok = stop_supervised({Vws.CEC.Workstation, ws})
      assert eventually(fn -> Client.info(client).peer == nil end)
      assert {:error, %ClientError{reason: :closed}} = Client.status(client, "TRAYS")
    end
  end
end
