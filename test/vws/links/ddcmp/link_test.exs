defmodule Vws.Links.DDCMP.LinkTest do
  # The DDCMP V4.1 state table, row by row: the test process plays the peer with raw frames
  # (Vws.Test.DDCMPPeer) and asserts the exact frames the link sends back.
  use ExUnit.Case, async: true

  alias Vws.Codecs.CRC16
  alias Vws.Links.DDCMP
  alias Vws.Links.DDCMP.Frame
  alias Vws.Links.DDCMP.Frame.Maintenance
  alias Vws.Test.DDCMPPeer, as: Peer

  # Timers that must not fire during a row; rows about timers set their own, small ones.
  @never 600_000
  # How long "nothing more is sent" is watched for. Only a wrong link could fail these checks
  # late, never a slow machine.
  @quiet 150

  # Wire bytes from PROTOCOLS.md §3 (computed with python3, not with our codec).
  @strt_wire "05 06 c0 00 00 01 75 95 ff"
  @ack0_wire "05 01 00 00 00 01 fc 55 ff"
  @rep1_wire "05 03 00 00 01 01 84 05 ff"
  @nak3_r1_wire "05 02 03 01 00 01 e9 d1 ff"

  defp hex(s), do: s |> String.replace(" ", "") |> Base.decode16!(case: :lower)

  # --- driving the link --------------------------------------------------------------------------

  defp start(opts) do
    {peer_opts, opts} = Keyword.split(opts, [:peer_max_data])
    {:ok, peer} = Peer.start_link(max_data: Keyword.get(peer_opts, :peer_max_data, 4096))

    opts =
      Keyword.merge(
        [
          endpoint: Peer.endpoint(peer),
          owner: self(),
          rep_timeout: @never,
          start_timeout: @never
        ],
        opts
      )

    link = start_supervised!({DDCMP, opts})
    assert_receive {:peer_connected, ^peer}, 5000
    {link, peer}
  end

  defp to_state(:istrt, opts) do
    {link, peer} = start(opts)

    if Keyword.get(opts, :role, :active) == :active do
      expect(peer, Frame.strt())
    end

    {link, peer}
  end

  defp to_state(:astrt, opts) do
    {link, peer} = to_state(:istrt, opts)
    Peer.send_frames(peer, Frame.strt())
    expect(peer, Frame.stack())
    {link, peer}
  end

  defp to_state(:running, opts) do
    {link, peer} = to_state(:istrt, Keyword.put_new(opts, :role, :active))
    Peer.send_frames(peer, Frame.stack())
    expect(peer, Frame.ack(0))
    assert_receive {:ddcmp, ^link, :up}, 2000
    {link, peer}
  end

  defp to_state(:halted, opts) do
    {link, peer} = to_state(:running, opts)
    Peer.send_frames(peer, %Maintenance{data: "boot"})
    assert_receive {:ddcmp, ^link, {:down, :maintenance}}, 2000
    {link, peer}
  end

  defp expect(peer, frame) do
    assert_receive {:peer_frame, ^peer, received}, 2000
    assert received == frame
  end

  # The next bytes on the wire, however the transport chunked them.
  defp expect_raw(peer, expected, acc \\ <<>>)

  defp expect_raw(peer, expected, acc) when byte_size(acc) < byte_size(expected) do
    assert_receive {:peer_raw, ^peer, bytes}, 2000
    expect_raw(peer, expected, acc <> bytes)
  end

  defp expect_raw(_peer, expected, acc), do: assert(acc == expected)

  defp quiet(peer) do
    refute_receive {:peer_frame, ^peer, _}, @quiet
    refute_received {:peer_bad, ^peer, _}
  end

  defp state(link), do: DDCMP.info(link).state

  defp send!(link, bytes), do: assert(:ok = DDCMP.send_data(link, bytes))

  defp feed(peer, {:raw, bytes}), do: Peer.send_raw(peer, bytes)
  defp feed(peer, frame), do: Peer.send_frames(peer, frame)

  # --- wire faults ---------------------------------------------------------------------------------

  defp flip(bytes, at) do
    <<head::binary-size(at), byte, tail::binary>> = bytes
    <<head::binary, Bitwise.bxor(byte, 0x20), tail::binary>>
  end

  defp wire(frame), do: frame |> Frame.encode() |> IO.iodata_to_binary()

  # A data message whose RESP byte was hit on the line: the header check fails.
  defp bad_header, do: {:raw, wire(Frame.data(1, 0, "HELLO")) |> flip(3)}
  # A good header whose data was hit: the data check fails.
  defp bad_data(num, resp), do: {:raw, wire(Frame.data(num, resp, "HELLO")) |> flip(9)}
  # A control message with an unknown TYPE but a good check.
  defp bad_format do
    header = <<5, 4, 0, 0, 0, 1>>
    {:raw, header <> CRC16.encode(CRC16.compute(header)) <> <<0xFF>>}
  end

  defp too_long, do: {:raw, wire(Frame.data(1, 0, "0123456789"))}

  # --- the table ---------------------------------------------------------------------------------

  # {state, event, input, frames sent back, next state, owner messages, link options}
  @rows [
    {:istrt, "STRT", [:strt], [:stack], :astrt, [], []},
    {:istrt, "STACK", [:stack], [{:ack, 0}], :running, [:up], []},
    {:istrt, "ACK", [{:ack, 0}], [], :istrt, [], []},
    {:istrt, "NAK", [{:nak, 1, 0}], [], :istrt, [], []},
    {:istrt, "REP", [{:rep, 0}], [], :istrt, [], []},
    {:istrt, "data", [{:data, 1, 0, "x"}], [], :istrt, [], []},
    {:istrt, "header CRC error", [:bad_header], [], :istrt, [], []},
    {:istrt, "data CRC error", [{:bad_data, 1, 0}], [], :istrt, [], []},
    {:istrt, "maintenance", [:maintenance], [], :halted, [], []},
    {:istrt, "STRT (passive: waits for it)", [:strt], [:stack], :astrt, [], [role: :passive]},
    {:istrt, "STACK (passive)", [:stack], [{:ack, 0}], :running, [:up], [role: :passive]},
    {:astrt, "STACK", [:stack], [{:ack, 0}], :running, [:up], []},
    {:astrt, "ACK RESP=0", [{:ack, 0}], [], :running, [:up], []},
    {:astrt, "ACK RESP=1", [{:ack, 1}], [], :astrt, [], []},
    {:astrt, "data RESP=0", [{:data, 1, 0, "hi"}], [{:ack, 1}], :running, [:up, {:data, "hi"}],
     []},
    {:astrt, "data RESP=3", [{:data, 1, 3, "hi"}], [], :astrt, [], []},
    {:astrt, "STRT", [:strt], [:stack], :astrt, [], []},
    {:astrt, "NAK", [{:nak, 2, 0}], [], :astrt, [], []},
    {:astrt, "REP", [{:rep, 0}], [], :astrt, [], []},
    {:astrt, "header CRC error", [:bad_header], [], :astrt, [], []},
    {:astrt, "maintenance", [:maintenance], [], :halted, [], []},
    {:running, "data NUM=R+1", [{:data, 1, 0, "a"}], [{:ack, 1}], :running, [{:data, "a"}], []},
    {:running, "data NUM=R+1, empty", [{:data, 1, 0, ""}], [{:ack, 1}], :running, [{:data, ""}],
     []},
    {:running, "two data in one chunk", [[{:data, 1, 0, "a"}, {:data, 2, 0, "b"}]], [{:ack, 2}],
     :running, [{:data, "a"}, {:data, "b"}], []},
    {:running, "data NUM=R+2 (discarded), then REP(0)", [{:data, 2, 0, "a"}, {:rep, 0}],
     [{:ack, 0}], :running, [], []},
    {:running, "REP NUM=R", [{:rep, 0}], [{:ack, 0}], :running, [], []},
    {:running, "REP NUM≠R", [{:rep, 1}], [{:nak, 3, 0}], :running, [], []},
    {:running, "STACK", [:stack], [{:ack, 0}], :running, [], []},
    {:running, "ACK with nothing outstanding", [{:ack, 5}], [], :running, [], []},
    {:running, "NAK with nothing outstanding", [{:nak, 1, 9}], [], :running, [], []},
    {:running, "header CRC error", [:bad_header], [{:nak, 1, 0}], :running, [], []},
    {:running, "data CRC error", [{:bad_data, 1, 0}], [{:nak, 2, 0}], :running, [], []},
    {:running, "message too long", [:too_long], [{:nak, 16, 0}], :running, [], [max_data: 8]},
    {:running, "header format error", [:bad_format], [{:nak, 17, 0}], :running, [], []},
    {:running, "STRT (active: restarts)", [:strt], [:strt], :istrt, [:peer_restarted], []},
    {:running, "STRT (passive: answers)", [:strt], [:stack], :astrt, [:peer_restarted],
     [role: :passive]},
    {:running, "maintenance", [:maintenance], [], :halted, [{:down, :maintenance}], []},
    {:halted, "STRT", [:strt], [], :halted, [], []},
    {:halted, "data", [{:data, 1, 0, "x"}], [], :halted, [], []}
  ]

  defp build(:strt), do: Frame.strt()
  defp build(:stack), do: Frame.stack()
  defp build({:ack, r}), do: Frame.ack(r)
  defp build({:nak, reason, r}), do: Frame.nak(reason, r)
  defp build({:rep, n}), do: Frame.rep(n)
  defp build({:data, n, r, bytes}), do: Frame.data(n, r, bytes)
  defp build(:maintenance), do: %Maintenance{data: "boot"}
  defp build(:bad_header), do: bad_header()
  defp build({:bad_data, n, r}), do: bad_data(n, r)
  defp build(:bad_format), do: bad_format()
  defp build(:too_long), do: too_long()

  describe "state table" do
    for {from, event, inputs, replies, next, owner, opts} <- @rows do
      @row {from, inputs, replies, next, owner, opts}
      test "#{String.upcase(to_string(from))} + #{event} -> #{String.upcase(to_string(next))}" do
        {from, inputs, replies, next, owner, opts} = @row
        {link, peer} = to_state(from, opts)

        for input <- inputs do
          case input do
            chunk when is_list(chunk) -> Peer.send_frames(peer, Enum.map(chunk, &build/1))
            input -> feed(peer, build(input))
          end
        end

        for reply <- replies, do: expect(peer, build(reply))
        quiet(peer)
        for message <- owner, do: assert_receive({:ddcmp, ^link, ^message}, 2000)
        refute_received {:ddcmp, ^link, _}
        assert state(link) == next
      end
    end
  end

  describe "exact bytes on the wire (PROTOCOLS.md §3 vectors)" do
    test "STRT, ACK(0), REP(1) and NAK(3, R=1), each followed by one DEL" do
      {link, peer} = start(rep_timeout: 200)
      expect_raw(peer, hex(@strt_wire))
      Peer.send_frames(peer, Frame.stack())
      expect_raw(peer, hex(@ack0_wire))
      assert_receive {:ddcmp, ^link, :up}

      Peer.send_frames(peer, Frame.data(1, 0, "x"))
      expect_raw(peer, hex("05 01 00 01 00 01 ad 95 ff"))
      Peer.send_frames(peer, Frame.rep(2))
      expect_raw(peer, hex(@nak3_r1_wire))

      # Not acknowledged: the reply timer asks with REP(N = 1).
      send!(link, "y")
      expect_raw(peer, wire(Frame.data(1, 1, "y")) <> hex(@rep1_wire))
    end
  end

  describe "start-up timers" do
    test "ISTRT resends STRT every start_timeout" do
      {_link, peer} = start(start_timeout: 30)
      for _ <- 1..3, do: expect(peer, Frame.strt())
    end

    test "ASTRT resends STACK every start_timeout, and ACK(0) ends it" do
      {link, peer} = start(start_timeout: 30)
      expect(peer, Frame.strt())
      Peer.send_frames(peer, Frame.strt())

      # STRT resends already in flight may precede the STACKs.
      stacks =
        Stream.repeatedly(fn ->
          assert_receive {:peer_frame, ^peer, frame}, 2000
          frame
        end)
        |> Stream.reject(&(&1 == Frame.strt()))
        |> Enum.take(3)

      assert stacks == List.duplicate(Frame.stack(), 3)
      Peer.send_frames(peer, Frame.ack(0))
      assert_receive {:ddcmp, ^link, :up}, 2000
    end

    test "a passive link sends nothing until the peer's STRT" do
      {link, peer} = start(role: :passive, start_timeout: 30)
      quiet(peer)
      assert state(link) == :istrt
    end
  end

  describe "RUNNING, sending" do
    test "data carries NUM and RESP; an ACK in range completes it" do
      {link, peer} = to_state(:running, [])
      Peer.send_frames(peer, Frame.data(1, 0, "in"))
      expect(peer, Frame.ack(1))
      assert_receive {:ddcmp, ^link, {:data, "in"}}

      send!(link, ["o", ?u, "t"])
      expect(peer, Frame.data(1, 1, "out"))
      assert %{n: 1, a: 0, outstanding: 1} = DDCMP.info(link)

      Peer.send_frames(peer, Frame.ack(1))
      quiet(peer)

      assert %{n: 1, a: 1, t: 2, outstanding: 0, counters: %{sent: 1, received: 1}} =
               DDCMP.info(link)
    end

    test "the window limits outstanding messages; acknowledgements open it" do
      {link, peer} = to_state(:running, window: 3)
      for i <- 1..5, do: send!(link, "m#{i}")
      for i <- 1..3, do: expect(peer, Frame.data(i, 0, "m#{i}"))
      quiet(peer)
      assert %{outstanding: 3, queue: 2} = DDCMP.info(link)

      # RESP in a data message acknowledges too.
      Peer.send_frames(peer, Frame.data(1, 2, "peer"))
      expect(peer, Frame.data(4, 1, "m4"))
      expect(peer, Frame.data(5, 1, "m5"))
      quiet(peer)
      assert %{a: 2, n: 5, outstanding: 3, queue: 0} = DDCMP.info(link)
    end

    test "RESP outside A < RESP <= N is ignored" do
      {link, peer} = to_state(:running, [])
      send!(link, "a")
      send!(link, "b")
      expect(peer, Frame.data(1, 0, "a"))
      expect(peer, Frame.data(2, 0, "b"))

      Peer.send_frames(peer, Frame.ack(3))
      Peer.send_frames(peer, Frame.ack(0))
      Peer.send_frames(peer, Frame.ack(200))
      quiet(peer)
      assert %{a: 0, outstanding: 2} = DDCMP.info(link)
    end

    test "a NAK in range acknowledges up to RESP and retransmits from A+1" do
      {link, peer} = to_state(:running, [])
      for m <- ~w(a b c), do: send!(link, m)
      for {m, i} <- Enum.with_index(~w(a b c), 1), do: expect(peer, Frame.data(i, 0, m))

      Peer.send_frames(peer, Frame.nak(:data_crc, 1))
      expect(peer, Frame.data(2, 0, "b"))
      expect(peer, Frame.data(3, 0, "c"))
      quiet(peer)

      assert %{a: 1, outstanding: 2, counters: %{retransmitted: 2, naks_received: 1}} =
               DDCMP.info(link)

      # Out of range: A <= RESP <= N fails.
      Peer.send_frames(peer, Frame.nak(:data_crc, 7))
      quiet(peer)
    end

    test "a NAK with RESP = A retransmits everything outstanding" do
      {link, peer} = to_state(:running, [])
      send!(link, "a")
      expect(peer, Frame.data(1, 0, "a"))
      Peer.send_frames(peer, Frame.nak(:header_crc, 0))
      expect(peer, Frame.data(1, 0, "a"))
      Peer.send_frames(peer, Frame.ack(1))
      quiet(peer)
      assert %{a: 1, outstanding: 0} = DDCMP.info(link)
    end

    test "requests before RUNNING wait for it, in order" do
      {link, peer} = to_state(:istrt, [])
      send!(link, "early 1")
      send!(link, "early 2")
      quiet(peer)

      Peer.send_frames(peer, Frame.stack())
      expect(peer, Frame.ack(0))
      expect(peer, Frame.data(1, 0, "early 1"))
      expect(peer, Frame.data(2, 0, "early 2"))
      assert_receive {:ddcmp, ^link, :up}
    end

    test "a message longer than max_data is refused" do
      {link, _peer} = to_state(:running, max_data: 8)
      assert DDCMP.send_data(link, "123456789") == {:error, :too_long}
      assert DDCMP.send_data(link, "12345678") == :ok
    end
  end

  describe "corruption and loss" do
    test "a corrupted data message is NAKed (2), retransmitted and delivered once" do
      {link, peer} = to_state(:running, [])
      feed(peer, bad_data(1, 0))
      expect(peer, Frame.nak(:data_crc, 0))
      Peer.send_frames(peer, Frame.data(1, 0, "HELLO"))
      expect(peer, Frame.ack(1))
      assert_receive {:ddcmp, ^link, {:data, "HELLO"}}
      quiet(peer)
      refute_received {:ddcmp, ^link, {:data, _}}
      assert %{counters: %{data_crc_errors: 1, naks_sent: 1, received: 1}} = DDCMP.info(link)
    end

    test "a duplicate is discarded; a REP then shows R unchanged" do
      {link, peer} = to_state(:running, [])
      Peer.send_frames(peer, Frame.data(1, 0, "a"))
      expect(peer, Frame.ack(1))
      Peer.send_frames(peer, Frame.data(1, 0, "a"))
      quiet(peer)
      Peer.send_frames(peer, Frame.rep(1))
      expect(peer, Frame.ack(1))
      assert_receive {:ddcmp, ^link, {:data, "a"}}
      refute_received {:ddcmp, ^link, {:data, _}}
    end

    test "a corrupted data message still acknowledges by its (good) header's RESP" do
      {link, peer} = to_state(:running, [])
      send!(link, "x")
      expect(peer, Frame.data(1, 0, "x"))
      feed(peer, bad_data(1, 1))
      expect(peer, Frame.nak(:data_crc, 0))
      assert %{a: 1, outstanding: 0} = DDCMP.info(link)
    end

    test "a lost ACK: the reply timer sends REP(N), the ACK it brings completes the message" do
      {link, peer} = to_state(:running, rep_timeout: 40)
      send!(link, "x")
      expect(peer, Frame.data(1, 0, "x"))
      expect(peer, Frame.rep(1))
      Peer.send_frames(peer, Frame.ack(1))
      # The timer stops with nothing outstanding: no more REPs.
      refute_receive {:peer_frame, ^peer, _}, 300

      assert %{a: 1, outstanding: 0, counters: %{reps_sent: reps, timeouts: reps}} =
               DDCMP.info(link)
    end

    test "a lost data message: REP(N) is answered NAK(3) and the message is sent again" do
      {link, peer} = to_state(:running, rep_timeout: 40)
      send!(link, "x")
      expect(peer, Frame.data(1, 0, "x"))
      expect(peer, Frame.rep(1))
      Peer.send_frames(peer, Frame.nak(:rep_response, 0))
      expect(peer, Frame.data(1, 0, "x"))
      Peer.send_frames(peer, Frame.ack(1))
      assert %{a: 1} = DDCMP.info(link)
    end

    test "8 successive timeouts: down, and start-up again" do
      {link, peer} = to_state(:running, rep_timeout: 20)
      send!(link, "x")
      expect(peer, Frame.data(1, 0, "x"))
      for _ <- 1..7, do: expect(peer, Frame.rep(1))
      expect(peer, Frame.strt())
      assert_receive {:ddcmp, ^link, {:down, :too_many_failures}}, 2000
      assert %{state: :istrt, outstanding: 0, counters: %{timeouts: 8}} = DDCMP.info(link)

      # Back up: nothing of the old stream is sent again.
      Peer.send_frames(peer, Frame.stack())
      expect(peer, Frame.ack(0))
      assert_receive {:ddcmp, ^link, :up}
      quiet(peer)
    end

    test "a passive link that declares its link down starts up again itself: STRT" do
      # the peer may have nothing outstanding and never learn otherwise (a VAL II simulator
      # waited in ISTRT while the CEC waited, RUNNING, for a response it had lost)
      {link, peer} = start(role: :passive, rep_timeout: 20)
      Peer.send_frames(peer, Frame.strt())
      expect(peer, Frame.stack())
      Peer.send_frames(peer, Frame.ack(0))
      assert_receive {:ddcmp, ^link, :up}, 2000

      send!(link, "x")
      expect(peer, Frame.data(1, 0, "x"))
      for _ <- 1..7, do: expect(peer, Frame.rep(1))
      expect(peer, Frame.strt())
      assert_receive {:ddcmp, ^link, {:down, :too_many_failures}}, 2000

      Peer.send_frames(peer, Frame.stack())
      expect(peer, Frame.ack(0))
      assert_receive {:ddcmp, ^link, :up}
      quiet(peer)
    end

    test "successive NAKs count as failures too (max_failures: 3)" do
      {link, peer} = to_state(:running, max_failures: 3)
      send!(link, "x")
      expect(peer, Frame.data(1, 0, "x"))

      for _ <- 1..2 do
        Peer.send_frames(peer, Frame.nak(:data_crc, 0))
        expect(peer, Frame.data(1, 0, "x"))
      end

      Peer.send_frames(peer, Frame.nak(:data_crc, 0))
      expect(peer, Frame.strt())
      assert_receive {:ddcmp, ^link, {:down, :too_many_failures}}
    end

    test "an acknowledgement resets the failure count" do
      {link, peer} = to_state(:running, max_failures: 2)
      send!(link, "a")
      send!(link, "b")
      expect(peer, Frame.data(1, 0, "a"))
      expect(peer, Frame.data(2, 0, "b"))
      Peer.send_frames(peer, Frame.nak(:data_crc, 0))
      expect(peer, Frame.data(1, 0, "a"))
      expect(peer, Frame.data(2, 0, "b"))
      Peer.send_frames(peer, Frame.ack(1))
      Peer.send_frames(peer, Frame.nak(:data_crc, 1))
      expect(peer, Frame.data(2, 0, "b"))
      quiet(peer)
      assert %{state: :running, failures: 1} = DDCMP.info(link)
    end
  end

  describe "restarts" do
    test "the peer restarts mid-stream: :peer_restarted, outstanding data dropped" do
      {link, peer} = to_state(:running, window: 2)
      for m <- ~w(a b c), do: send!(link, m)
      expect(peer, Frame.data(1, 0, "a"))
      expect(peer, Frame.data(2, 0, "b"))

      Peer.send_frames(peer, Frame.strt())
      assert_receive {:ddcmp, ^link, :peer_restarted}
      expect(peer, Frame.strt())

      assert %{state: :istrt, outstanding: 0, queue: 0, counters: %{restarts: 1}} =
               DDCMP.info(link)

      Peer.send_frames(peer, Frame.stack())
      expect(peer, Frame.ack(0))
      assert_receive {:ddcmp, ^link, :up}
      send!(link, "d")
      expect(peer, Frame.data(1, 0, "d"))
    end

    test "restart/1 between commands: {:down, :restart}, STRT, then up again" do
      {link, peer} = to_state(:running, [])
      assert DDCMP.restart(link) == :ok
      assert_receive {:ddcmp, ^link, {:down, :restart}}
      expect(peer, Frame.strt())
      Peer.send_frames(peer, Frame.stack())
      expect(peer, Frame.ack(0))
      assert_receive {:ddcmp, ^link, :up}
    end

    test "restart/1 in ISTRT sends STRT again, without a :down" do
      {link, peer} = to_state(:istrt, [])
      assert DDCMP.restart(link) == :ok
      expect(peer, Frame.strt())
      refute_received {:ddcmp, ^link, _}
    end

    test "a maintenance-halted link ignores everything until restart/1" do
      {link, peer} = to_state(:halted, [])
      send!(link, "later")
      quiet(peer)
      assert %{state: :halted, halt_reason: :maintenance} = DDCMP.info(link)

      assert DDCMP.restart(link) == :ok
      expect(peer, Frame.strt())
      Peer.send_frames(peer, Frame.stack())
      expect(peer, Frame.ack(0))
      expect(peer, Frame.data(1, 0, "later"))
    end
  end

  describe "transport" do
    test "the peer goes away: {:down, :closed}, the link dials again and restarts" do
      {link, peer} = to_state(:running, backoff: {10, 50})
      Peer.drop_connection(peer)
      assert_receive {:ddcmp, ^link, {:down, :closed}}, 2000
      assert_receive {:peer_connected, ^peer}, 5000
      expect(peer, Frame.strt())
    end

    test "a handed-over connection (:conn): the link takes it; its close ends the link" do
      name = "ddcmp-conn-#{System.unique_integer([:positive])}"
      {:ok, listener} = Vws.Links.Transport.listen("loopback:" <> name)
      {:ok, conn} = Vws.Links.Transport.connect("loopback:" <> name)
      {:ok, far} = Vws.Links.Transport.accept(listener, 5000)

      {:ok, link} =
        DDCMP.start_link(conn: conn, role: :passive, rep_timeout: @never, start_timeout: @never)

      ref = Process.monitor(link)
      :ok = Vws.Links.Transport.send(far, Frame.encode(Frame.strt()))
      :ok = Vws.Links.Transport.activate(far)
      assert_receive msg, 2000
      assert Vws.Links.Transport.handle_message(far, msg) == {:data, wire(Frame.stack())}

      Vws.Links.Transport.close(far)
      assert_receive {:ddcmp, ^link, {:down, :closed}}, 2000
      assert_receive {:DOWN, ^ref, :process, ^link, :normal}, 2000
    end

    test "unexpected messages are logged, counted and survived" do
      {link, peer} = to_state(:running, [])
      send(link, :stray)
      assert %{state: :running, counters: %{unexpected: 1}} = DDCMP.info(link)
      send!(link, "still")
      expect(peer, Frame.data(1, 0, "still"))
    end
  end
end
