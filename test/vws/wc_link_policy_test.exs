defmodule Vws.WCLinkPolicyTest do
  # SUN_COMM's WC port under its policy (issue 16): who may connect, when a new connection may
  # replace the WC, and a WC that never reads. Over real TCP; 127.0.0.2 (Linux routes all of
  # 127/8 to lo) plays a host that is not on the allow-list.
  use ExUnit.Case, async: true

  import ExUnit.CaptureLog
  import Vws.Test.Eventually

  alias Vws.Test.{WCPeer, Workstation}

  @intruder {127, 0, 0, 2}

  defp start(sun_comm) do
    %{ws: ws} = Workstation.start(wc: "tcp://127.0.0.1:0", sun_comm: sun_comm)

    assert eventually(fn -> Vws.CEC.SunComm.listening(ws) != nil end)

    %{
      ws: ws,
      wc: to_string(Vws.CEC.SunComm.listening(ws)),
      port: Vws.CEC.SunComm.listening(ws).port
    }
  end

  defp raw_connect(port, from) do
    :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, ip: from])
  end

  test "a connection from an address not on the allow-list is closed at once; the WC keeps its link" do
    %{ws: ws, wc: wc, port: port} = start(allow: "127.0.0.1")
    {:ok, peer} = WCPeer.connect(wc)
    assert WCPeer.status(peer, 1, 1, "ROBOT_CMD") == "0000NONE"

    log =
      capture_log(fn ->
        {:ok, intruder} = raw_connect(port, @intruder)
        # it may say anything: nothing is read, nothing answered, and it is closed
        _ = :gen_tcp.send(intruder, WCPeer.string(2, [{"S", 2, "ROBOT_CMD"}]))
        assert {:error, _} = :gen_tcp.recv(intruder, 0, 5_000)
        :gen_tcp.close(intruder)
      end)

    assert log =~ "refused a connection from tcp://127.0.0.2:"
    assert log =~ "127.0.0.1/32"
    assert WCPeer.status(peer, 3, 3, "ROBOT_CMD") == "0000NONE"
    info = Vws.CEC.SunComm.info(ws)
    assert info.counters.connections == 1
    assert info.peer =~ "tcp://127.0.0.1:"
  end

  test "by default only loopback may connect; the allow-list is parsed strictly" do
    %{port: port} = start([])
    # 127.0.0.2 is loopback too: allowed (it then talks to SUN_COMM)
    {:ok, s} = raw_connect(port, @intruder)
    :ok = :gen_tcp.send(s, WCPeer.string(1, [{"S", 1, "ROBOT_CMD"}]))
    assert {:ok, _answer} = :gen_tcp.recv(s, 0, 5_000)

    assert {:error, _} = Vws.Links.Transport.Policy.parse_allow("10.0.0.0/33")
    assert {:error, _} = Vws.Links.Transport.Policy.parse_allow("10.0.0.300")
    assert {:ok, [{{10, 0, 0, 0}, 24}]} = Vws.Links.Transport.Policy.parse_allow("10.0.0.0/24")
    refute Vws.Links.Transport.Policy.allowed?(:loopback, {10, 0, 0, 5})
    assert Vws.Links.Transport.Policy.allowed?(:loopback, {0, 0, 0, 0, 0, 0xFFFF, 0x7F00, 1})
  end

  test "SUN_COMM refuses to listen on a non-loopback address without an allow-list" do
    ws = "policy-#{System.unique_integer([:positive])}"
    start_supervised!({Vws.CEC.Mailbox.Owner, workstation: ws})

    capture_log(fn ->
      assert {:error, {{:wc_link_policy, message}, _}} =
               start_supervised({Vws.CEC.SunComm, workstation: ws, wc: "tcp://0.0.0.0:0"})

      assert message =~ "needs an allow-list"
      assert message =~ "--wc-allow"
    end)

    assert {:ok, _} =
             start_supervised(
               {Vws.CEC.SunComm, workstation: ws, wc: "tcp://0.0.0.0:0", allow: "10.0.0.0/24"}
             )
  end

  test "a new WC replaces the current one only after takeover_after of silence; both peers logged" do
    # no grace: a refused newcomer is closed at once (the grace has a test of its own)
    %{ws: ws, wc: wc} = start(takeover_after: 1_000, takeover_grace: 0)
    {:ok, first} = WCPeer.connect(wc)
    assert WCPeer.status(first, 1, 1, "ROBOT_CMD") == "0000NONE"

    log =
      capture_log(fn ->
        {:ok, second} = WCPeer.connect(wc)
        # refused: closed without an answer; the first WC still works
        assert WCPeer.recv_line(second, 2_000) in [{:timeout, :closed}, :closed]
        assert WCPeer.status(first, 2, 2, "ROBOT_CMD") == "0000NONE"
      end)

    assert log =~
             ~r/WC connection from tcp:\/\/127\.0\.0\.1:\d+ refused: the WC on tcp:\/\/127\.0\.0\.1:\d+ was heard/

    # the first WC falls silent (a half-open link): after takeover_after a newcomer gets in
    heard = System.monotonic_time(:millisecond)

    log =
      capture_log(fn ->
        third =
          Enum.find_value(1..100, fn _ ->
            Process.sleep(100)
            {:ok, p} = WCPeer.connect(wc)
            # in only when answered: a refused newcomer is closed unanswered (under load, not
            # closed yet after a few ms, it looked open and was taken for the third WC)
            # (the send fails when it was closed already)
            _ = WCPeer.send_raw(p, WCPeer.string(4, [{"S", 4, "ROBOT_CMD"}]))

            case WCPeer.recv_line(p, 2_000) do
              line when is_binary(line) -> p
              {:timeout, _closed_or_silent} -> nil
            end
          end)

        assert System.monotonic_time(:millisecond) - heard >= 1_000
        assert WCPeer.status(third, 3, 3, "ROBOT_CMD") == "0000NONE"
        assert WCPeer.recv_line(first, 2_000) in [{:timeout, :closed}, :closed]
      end)

    assert log =~ ~r/takes over from tcp:\/\/127\.0\.0\.1:\d+/
    assert Vws.CEC.SunComm.info(ws).counters.connections == 2
  end

  test "a WC that closes its connection and opens the next at once is let in, not refused" do
    # one connection per command (bin/vws-wc, socat): the new connection can reach SUN_COMM
    # before the old one's close does (found by the acceptance tests: a second request was
    # closed unanswered). Forced here: SUN_COMM is held while the newcomer's acceptance and
    # then the old connection's close are queued, in that order.
    %{ws: ws, wc: wc} = start([])
    sun_comm = GenServer.whereis(Vws.Names.via(ws, :sun_comm))
    {:ok, first} = WCPeer.connect(wc)
    assert WCPeer.status(first, 1, 1, "ROBOT_CMD") == "0000NONE"

    :ok = :sys.suspend(sun_comm)

    queued = fn n ->
      eventually(fn -> Process.info(sun_comm, :message_queue_len) |> elem(1) >= n end)
    end

    {:ok, second} = WCPeer.connect(wc)
    assert queued.(1)
    WCPeer.close(first)
    assert queued.(2)
    :ok = :sys.resume(sun_comm)

    assert WCPeer.status(second, 2, 2, "ROBOT_CMD") == "0000NONE"
    assert Vws.CEC.SunComm.info(ws).counters.connections == 2
  end

  test "a second newcomer while one waits, and a newcomer while the WC stays, are refused" do
    %{wc: wc} = start(takeover_grace: 300)
    {:ok, first} = WCPeer.connect(wc)
    assert WCPeer.status(first, 1, 1, "ROBOT_CMD") == "0000NONE"

    capture_log(fn ->
      {:ok, second} = WCPeer.connect(wc)
      {:ok, third} = WCPeer.connect(wc)
      assert WCPeer.recv_line(third, 2_000) in [{:timeout, :closed}, :closed]
      assert WCPeer.recv_line(second, 2_000) in [{:timeout, :closed}, :closed]
    end)

    assert WCPeer.status(first, 2, 2, "ROBOT_CMD") == "0000NONE"
  end

  test "a WC that sends and never reads is dropped after send_timeout; SUN_COMM answers the next WC" do
    %{ws: ws, wc: wc, port: port} = start(send_timeout: 500)

    {:ok, hog} = :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, recbuf: 2048])

    parent = self()
    query = WCPeer.string(1, [{"S", 1, "ROBOT_CMD"}])

    capture_log(fn ->
      spawn_link(fn ->
        # sends the same status query for ever, reads nothing
        result =
          Enum.reduce_while(Stream.cycle([query]), 0, fn q, n ->
            case :gen_tcp.send(hog, :binary.copy(q, 100)) do
              :ok -> {:cont, n + 1}
              {:error, reason} -> {:halt, reason}
            end
          end)

        send(parent, {:hog_done, result})
      end)

      assert eventually(fn -> Vws.CEC.SunComm.info(ws).peer == nil end, 20_000)
      assert_receive {:hog_done, _closed}, 20_000
    end)

    {:ok, peer} = WCPeer.connect(wc)
    assert WCPeer.status(peer, 2, 2, "ROBOT_CMD") == "0000NONE"
  end
end
