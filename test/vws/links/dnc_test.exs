defmodule Vws.Links.DNCTest do
  # The link state machine against a raw peer scripted byte by byte (PROTOCOLS.md §2).
  use ExUnit.Case, async: true

  alias Vws.Links.DNC
  alias Vws.Links.DNC.{Frame, LinkError}
  alias Vws.Links.DNC.Frame.{Command, Text}
  alias Vws.Test.DNCPeer
  alias Vws.Links.Transport
  import Vws.Test.Eventually

  doctest DNC

  @enq <<0x05>>
  @enq_del <<0x05, 0x7F>>
  @eot <<0x04>>
  @eot_del <<0x04, 0x7F>>
  @ack0 <<0x10, ?0>>
  @ack1 <<0x10, ?1>>
  @wack <<0x10, ?;>>
  @nak <<0x15>>

  # seed §3.2.2 and §3.2.7; BCCs from the python3-computed golden vectors of frame_test.exs
  @sns %Command{direction: :send, check: :lrc, operation: :part_program}
  @sns_bytes <<0x01, "SNS", 0x02, 0x03, 0x4F>>
  @rnl %Command{direction: :receive, check: :lrc, operation: :status}
  @rnl_bytes <<0x01, "RNL", 0x02, 0x03, 0x51>>

  defp text(t, check \\ :lrc),
    do: Frame.encode(%Text{text: t}, check: check) |> IO.iodata_to_binary()

  setup do
    name = "dnc-test-#{System.unique_integer([:positive])}"
    {:ok, listener} = Transport.listen("loopback:" <> name)
    on_exit(fn -> Transport.close_listener(listener) end)
    %{endpoint: "loopback:" <> name, listener: listener}
  end

  # A link that connects to the test's listener, and the raw peer on the other end.
  defp connected(ctx, opts \\ []) do
    opts = Keyword.merge([endpoint: ctx.endpoint, owner: self()], opts)
    link = start_supervised!({DNC, opts})
    {:ok, peer} = DNCPeer.accept(ctx.listener)
    assert_receive {:dnc, ^link, :connected}, 5_000
    {link, peer}
  end

  defp request(link, command, blocks, timeout \\ 20_000),
    do: Task.async(fn -> DNC.request(link, command, blocks, timeout) end)

  defp expect(peer, bytes), do: assert(DNCPeer.recv(peer, byte_size(bytes)) == bytes)

  describe "master: sending (S command)" do
    test "bid, command block, text blocks acknowledged ACK1, ACK0, ACK1, then EOT", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, ["O1\n", "N10 G00\n", "M30\n"])

      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("O1\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, text("N10 G00\n"))
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("M30\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot)

      assert Task.await(task) == {:ok, []}
      assert DNC.info(link).state == :idle
    end

    test "CRC mode: text blocks carry the command's check", ctx do
      {link, peer} = connected(ctx)
      command = %{@sns | check: :crc}
      task = request(link, command, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, <<0x01, 0x53, 0x43, 0x53, 0x02, 0x03, 0x20, 0xF8>>)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n", :crc))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    test "a NAK makes the block go again; the fourth NAK ends it with EOT and :nak_limit", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)

      for _ <- 1..4 do
        expect(peer, text("N10\n"))
        DNCPeer.send_raw(peer, @nak)
      end

      expect(peer, @eot)

      assert {:error, %LinkError{reason: :nak_limit, block: 2, count: 4}} = Task.await(task)
      assert DNC.info(link).counters.retransmissions == 3
    end

    test "a NAK then the acknowledgement: the transfer goes on", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @nak)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    test "no reply: ENQ asks for it again; a lost ACK is recovered", ctx do
      {link, peer} = connected(ctx, reply_timeout: 500)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      # our ACK1 is "lost": the link polls, and takes an acknowledgement that answers its ENQ
      # only when it comes twice (ACK0 and ACK1 differ in one bit)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    test "the reply to ENQ repeats the previous ACK: the block was lost and goes again", ctx do
      {link, peer} = connected(ctx, reply_timeout: 500)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    test "a wrong-parity acknowledgement is a lost reply: ENQ", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      # heard once in answer to an ENQ: asked again
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    # One flipped bit turns ACK0 into ACK1: the answer to an ENQ that says "the block you sent
    # arrived" counts only when it comes twice; a second answer that differs means it did not.
    test "an acknowledgement answering our ENQ counts only when it comes twice", ctx do
      {link, peer} = connected(ctx, reply_timeout: 500)
      task = request(link, @sns, ["N10\n", "N20\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      # N10 "lost"; the receiver's true answer (ACK1, the command block's) arrives flipped to ACK0
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      # the two answers differ: the second, ACK1, repeats the last one — N10 goes again
      expect(peer, text("N10\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, text("N20\n"))
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    test "a peer that never answers: 3 ENQs, then EOT and :no_reply", ctx do
      {link, peer} = connected(ctx, reply_timeout: 300)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      expect(peer, @enq <> @enq <> @enq <> @eot)
      assert {:error, %LinkError{reason: :no_reply, block: 1, count: 3}} = Task.await(task)

      assert LinkError.status_text(elem(Task.await(request(link, @sns, [], 50)), 1)) ==
               "DNC REQUEST TIMEOUT"
    end

    test "an unanswered bid is tried 1 + max_enqs times, then :no_answer_to_bid", ctx do
      {link, peer} = connected(ctx, reply_timeout: 100, max_enqs: 2)
      task = request(link, @sns, [])
      expect(peer, @enq <> @enq <> @enq <> @eot)
      assert {:error, %LinkError{reason: :no_answer_to_bid, count: 3}} = Task.await(task)
    end

    test "WACK: wait, then ENQ; the ACK that follows lets the transfer go on", ctx do
      {link, peer} = connected(ctx, wack_delay: 50)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @wack)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @wack)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
      assert DNC.info(link).counters.wacks_received == 2
    end

    test "WACK over max_wacks times running ends :wack_limit", ctx do
      {link, peer} = connected(ctx, wack_delay: 20, max_wacks: 2)
      task = request(link, @sns, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @wack)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @wack)
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @wack)
      expect(peer, @eot)
      assert {:error, %LinkError{reason: :wack_limit, count: 3}} = Task.await(task)
    end

    test "EOT from the peer in the middle of our transmission ends it :aborted", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, ["N10\n", "N20\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("N10\n"))
      DNCPeer.send_raw(peer, @eot_del)
      assert {:error, %LinkError{reason: :aborted, block: 2}} = Task.await(task)
    end

    test "text that cannot be sent is refused before anything goes on the line", ctx do
      {link, peer} = connected(ctx)
      assert {:error, %LinkError{reason: :invalid_text}} = DNC.request(link, @sns, [<<"N1", 3>>])

      assert {:error, %LinkError{reason: :invalid_text}} =
               DNC.request(link, @sns, [String.duplicate("X", 257)])

      assert DNCPeer.quiet?(peer, 50)
    end
  end

  describe "master: R command, then the slave role" do
    test "RNL: after our EOT the peer bids ENQ DEL and its blocks come back", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @rnl, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @rnl_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, text("STATE=IDLE;"))
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, text("PROG=000000;ALARM=0"))
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, @eot_del)
      assert Task.await(task) == {:ok, ["STATE=IDLE;", "PROG=000000;ALARM=0"]}
    end

    test "a damaged block is answered NAK, ENQ gets the last reply again", ctx do
      {link, peer} = connected(ctx)
      command = %{@rnl | check: :crc}
      task = request(link, command, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      assert <<0x01, "RCL", 0x02, 0x03, _, _>> = DNCPeer.recv(peer, 8)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      <<good::binary-size(6), bcc::binary-size(2)>> = text("ABCD", :crc)
      <<lo, hi>> = bcc
      DNCPeer.send_raw(peer, good <> <<Bitwise.bxor(lo, 0xFF), hi>>)
      expect(peer, @nak)
      DNCPeer.send_raw(peer, @enq)
      expect(peer, @nak)
      DNCPeer.send_raw(peer, good <> bcc)
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, @enq)
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, @eot_del)
      assert Task.await(task) == {:ok, ["ABCD"]}
    end

    test "our EOT after an R command lost on the line: EOT again until the peer bids", ctx do
      {link, peer} = connected(ctx, reply_timeout: 100, response_timeout: 10_000)
      task = request(link, @rnl, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @rnl_bytes)
      DNCPeer.send_raw(peer, @ack1)
      # the first EOT is taken as lost: the peer waits; the link sends it again, and again
      expect(peer, @eot)
      expect(peer, @eot)
      expect(peer, @eot)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, text("STATE=IDLE;"))
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, @eot_del)
      assert Task.await(task) == {:ok, ["STATE=IDLE;"]}
    end

    test "a peer that never bids after our R command: :no_response", ctx do
      {link, peer} = connected(ctx, response_timeout: 100)
      task = request(link, @rnl, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @rnl_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert {:error, %LinkError{reason: :no_response}} = Task.await(task)
    end

    test "a peer that stops sending half way: :receive_timeout, nothing partial", ctx do
      {link, peer} = connected(ctx, receive_timeout: 100)
      task = request(link, @rnl, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @rnl_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, text("PART"))
      expect(peer, @ack1)
      assert {:error, %LinkError{reason: :receive_timeout, count: 1}} = Task.await(task)
    end
  end

  describe "contention" do
    test "the CEC's bid meets the GE's ENQ DEL: it yields, receives, then bids again", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, [])
      expect(peer, @enq)
      # the GE bid at the same moment and keeps the line
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, text("STATE=IDLE;PROG=000000;ALARM=0"))
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, @eot_del)
      assert_receive {:dnc, ^link, {:unsolicited, ["STATE=IDLE;PROG=000000;ALARM=0"]}}, 5_000
      # our request goes out after the GE's EOT
      expect(peer, @enq)
      own_request_goes(peer, task)
      assert DNC.info(link).counters.contentions == 1
    end

    # The GE's R command (a remote request from its panel) wins the line from the CEC's bid for
    # an S request: up to the GE's EOT, after which the CEC owes an answer. Returns the link, the
    # peer, the request's task and the GE's command.
    defp yield_to_rcs(ctx, opts \\ []) do
      {link, peer} = connected(ctx, opts)
      task = request(link, @sns, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)

      rcs = %Command{
        direction: :receive,
        check: :crc,
        operation: :part_program,
        text: "000055.PRO"
      }

      DNCPeer.send_raw(peer, IO.iodata_to_binary(Frame.encode(rcs)))
      expect(peer, @ack1)
      {link, peer, task, rcs}
    end

    # the CEC's own S request, bid for again: it goes, and its caller has its answer
    defp own_request_goes(peer, task) do
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    # The CEC answers the GE's R command, then bids again for its own request. It used to forget
    # that request once the answer was out (the answer's transmission took its place): its
    # caller waited for ever, and MONARCH's status reads with it.
    test "the CEC's bid meets the GE's R command: it answers it, then bids again for its own",
         ctx do
      {link, peer, task, rcs} = yield_to_rcs(ctx)
      DNCPeer.send_raw(peer, @eot_del)
      assert_receive {:dnc, ^link, {:request, ref, ^rcs, []}}, 5_000

      assert DNC.answer(link, ref, ["%\nO55\nM30\n%\n"]) == :ok
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, text("%\nO55\nM30\n%\n", :crc))
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)

      # our own request's turn
      expect(peer, @enq)
      own_request_goes(peer, task)
    end

    test "an R command of the GE's left unanswered: the CEC's yielded request still goes", ctx do
      {link, peer, task, rcs} = yield_to_rcs(ctx, answer_timeout: 200)

      ExUnit.CaptureLog.capture_log(fn ->
        DNCPeer.send_raw(peer, @eot_del)
        assert_receive {:dnc, ^link, {:request, _ref, ^rcs, []}}, 5_000
        # no answer: after answer_timeout the line is ours again
        expect(peer, @enq)
      end)

      own_request_goes(peer, task)
    end

    test "the GE role keeps the line when its bid meets the CEC's ENQ", ctx do
      {link, peer} = connected(ctx, role: :ge)
      task = request(link, @sns, [])
      expect(peer, @enq_del)
      DNCPeer.send_raw(peer, @enq)
      assert DNCPeer.quiet?(peer, 100)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot_del)
      assert Task.await(task) == {:ok, []}
    end

    test "yielding over max_contention times running fails the request", ctx do
      {link, peer} = connected(ctx, max_contention: 1)
      task = request(link, @sns, [])

      for _ <- 1..2 do
        expect(peer, @enq)
        DNCPeer.send_raw(peer, @enq_del)
        expect(peer, @ack0)
        DNCPeer.send_raw(peer, @eot_del)
      end

      assert {:error, %LinkError{reason: :contention, count: 2}} = Task.await(task)
    end
  end

  describe "slave (the GE-2000's side)" do
    test "an S command and its text reach the owner after EOT", ctx do
      {link, peer} = connected(ctx, role: :ge)
      DNCPeer.send_raw(peer, @enq)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, @sns_bytes)
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, text("O1\n"))
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, text("M30\n"))
      expect(peer, @ack1)
      refute_received {:dnc, _, {:received, _, _}}
      DNCPeer.send_raw(peer, @eot)
      assert_receive {:dnc, ^link, {:received, @sns, ["O1\n", "M30\n"]}}, 5_000
    end

    # the peer (the CEC) sends the R command RNL to the link (the GE's side): its owner is told
    defp asked_rnl(link, peer) do
      DNCPeer.send_raw(peer, @enq)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, @rnl_bytes)
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, @eot)
      assert_receive {:dnc, ^link, {:request, ref, @rnl, []}}, 5_000
      ref
    end

    test "an R command: the owner answers, the link bids ENQ DEL and sends", ctx do
      {link, peer} = connected(ctx, role: :ge, reply_timeout: 500)
      ref = asked_rnl(link, peer)
      assert DNC.answer(link, ref, ["STATE=ACTIVE;", "PROG=000001;ALARM=0"]) == :ok
      expect(peer, @enq_del)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, text("STATE=ACTIVE;"))
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, text("PROG=000001;ALARM=0"))
      # a lost reply: the GE asks again (ENQ DEL, as it pads), and once more to be sure
      expect(peer, @enq_del)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @enq_del)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @eot_del)
      assert eventually(fn -> DNC.info(link).state == :idle end)
      assert DNC.answer(link, ref, []) == {:error, :not_asked}
    end
  end

  describe "an R command the owner leaves unanswered" do
    test "after answer_timeout the link says so, with where its owner was, and is idle again",
         ctx do
      {link, peer} = connected(ctx, role: :ge, reply_timeout: 500, answer_timeout: 200)

      log =
        ExUnit.CaptureLog.capture_log(fn ->
          ref = asked_rnl(link, peer)
          # the owner (this test) is held up elsewhere past the answer timeout
          Process.sleep(600)
          assert DNC.answer(link, ref, ["STATE=ACTIVE;"]) == {:error, :not_asked}
        end)

      assert log =~ "no answer to the peer's R command from the owner in time"
      assert log =~ "waiting for the link's owner, #{inspect(self())}, at"
      assert log =~ "Process.sleep/1"
      assert eventually(fn -> DNC.info(link).state == :idle end)
    end
  end

  # A block counts once: a copy of the block just accepted (the sender did not see, or misread,
  # its ACK; or it answered two NAKs) is acknowledged again with the same ACK and dropped. The same
  # receive logic serves the GE-2000 in an S transfer and the CEC in the answer to its R command.
  describe "receiving: every block counts once" do
    # seed 6 of the line test: a flipped bit turned the 0 of N60 into DLE (LRC 0x72, python3)
    @n60 "N60 G01 X6.5\n"
    @n60_broken <<0x02, "N6", 0x10, " G01 X6.5\n", 0x03, 0x72>>

    # GE role, slave: the peer bids and sends an SNS command; ACK1 answers it.
    defp ge_receiving(ctx) do
      {link, peer} = connected(ctx, role: :ge)
      DNCPeer.send_raw(peer, @enq)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, @sns_bytes)
      expect(peer, @ack1)
      {link, peer}
    end

    # CEC role: its RNL request is sent, the peer bids back; the task ends with what it got.
    defp cec_receiving(ctx) do
      {link, peer} = connected(ctx)
      task = request(link, @rnl, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @rnl_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      {link, peer, task}
    end

    defp finish(link, peer, :ge) do
      DNCPeer.send_raw(peer, @eot)
      assert_receive {:dnc, ^link, {:received, @sns, blocks}}, 5_000
      blocks
    end

    defp finish(_link, peer, task) do
      DNCPeer.send_raw(peer, @eot_del)
      assert {:ok, blocks} = Task.await(task)
      blocks
    end

    for side <- [:ge, :cec] do
      test "#{side}: a lost ACK, the block sent again: same ACK, the copy dropped", ctx do
        {link, peer, how} = receiving(unquote(side), ctx)
        {odd, even} = acks(unquote(side))
        DNCPeer.send_raw(peer, text("O1\n"))
        expect(peer, odd)
        # the sender did not see ACK0; it asks, is told, but (misreading it) sends the block again
        DNCPeer.send_raw(peer, @enq)
        expect(peer, odd)
        DNCPeer.send_raw(peer, text("O1\n"))
        expect(peer, odd)
        # a sender that resends on its reply timeout, without asking, gets the same answer
        DNCPeer.send_raw(peer, text("N10\n"))
        expect(peer, even)
        DNCPeer.send_raw(peer, text("N10\n"))
        expect(peer, even)
        DNCPeer.send_raw(peer, text("M30\n"))
        expect(peer, odd)
        assert finish(link, peer, how) == ["O1\n", "N10\n", "M30\n"]
        assert DNC.info(link).counters.duplicates == 2
      end

      test "#{side}: a block broken off by a control draws one NAK; sent again, it is taken once",
           ctx do
        {link, peer, how} = receiving(unquote(side), ctx)
        {odd, even} = acks(unquote(side))
        DNCPeer.send_raw(peer, text("O1\n"))
        expect(peer, odd)
        DNCPeer.send_raw(peer, @n60_broken)
        expect(peer, @nak)
        assert DNCPeer.quiet?(peer, 100)
        DNCPeer.send_raw(peer, text(@n60))
        expect(peer, even)
        DNCPeer.send_raw(peer, text("M30\n"))
        expect(peer, odd)
        assert finish(link, peer, how) == ["O1\n", @n60, "M30\n"]
        assert DNC.info(link).counters.naks_sent == 1
      end

      test "#{side}: two NAKs for one block bring two copies; the second is dropped", ctx do
        # the seed-6 failure: the first NAK is on its way when the sender polls, and the NAK
        # said again makes it send the block a second time
        {link, peer, how} = receiving(unquote(side), ctx)
        {odd, even} = acks(unquote(side))
        DNCPeer.send_raw(peer, text("O1\n"))
        expect(peer, odd)
        # a bad BCC (it is 0x72)
        DNCPeer.send_raw(peer, <<0x02, @n60::binary, 0x03, 0x00>>)
        expect(peer, @nak)
        DNCPeer.send_raw(peer, @enq)
        expect(peer, @nak)
        DNCPeer.send_raw(peer, text(@n60))
        expect(peer, even)
        DNCPeer.send_raw(peer, text(@n60))
        expect(peer, even)
        DNCPeer.send_raw(peer, text("M30\n"))
        expect(peer, odd)
        assert finish(link, peer, how) == ["O1\n", @n60, "M30\n"]
      end

      test "#{side}: after our NAK a copy of the block before replaces nothing", ctx do
        {link, peer, how} = receiving(unquote(side), ctx)
        {odd, even} = acks(unquote(side))
        DNCPeer.send_raw(peer, text("O1\n"))
        expect(peer, odd)
        # the next thing arrives damaged (the sender's poll, say): NAK; the sender, which never
        # saw ACK0, sends O1 again
        DNCPeer.send_raw(peer, @n60_broken)
        expect(peer, @nak)
        DNCPeer.send_raw(peer, text("O1\n"))
        expect(peer, odd)
        DNCPeer.send_raw(peer, text(@n60))
        expect(peer, even)
        assert finish(link, peer, how) == ["O1\n", @n60]
      end

      test "#{side}: a block equal to the last one accepted is a copy, however often it comes",
           ctx do
        {link, peer, how} = receiving(unquote(side), ctx)
        {odd, even} = acks(unquote(side))
        DNCPeer.send_raw(peer, text("G04 P1\n"))
        expect(peer, odd)

        # damaged replies can make a sender send a block again any number of times: each copy
        # is answered with that block's ACK again and dropped (a sender of ours never sends two
        # equal blocks in a row: Frame.split_text/2)
        for _ <- 1..4 do
          DNCPeer.send_raw(peer, text("G04 P1\n"))
          expect(peer, odd)
          DNCPeer.send_raw(peer, @enq)
          expect(peer, odd)
        end

        DNCPeer.send_raw(peer, text("M30\n"))
        expect(peer, even)
        assert finish(link, peer, how) == ["G04 P1\n", "M30\n"]
      end
    end

    defp receiving(:ge, ctx) do
      {link, peer} = ge_receiving(ctx)
      {link, peer, :ge}
    end

    defp receiving(:cec, ctx), do: cec_receiving(ctx)

    # The acknowledgements of the 1st, 3rd, … and the 2nd, 4th, … text block: the GE's text
    # follows the command block (ACK1), the CEC's is the first thing after the bid (ACK0).
    defp acks(:ge), do: {@ack0, @ack1}
    defp acks(:cec), do: {@ack1, @ack0}

    test "ge: the command block sent again is acknowledged again, not refused", ctx do
      {link, peer} = ge_receiving(ctx)
      DNCPeer.send_raw(peer, @sns_bytes)
      expect(peer, @ack1)
      DNCPeer.send_raw(peer, text("O1\n"))
      expect(peer, @ack0)
      assert finish(link, peer, :ge) == ["O1\n"]
    end
  end

  describe "connection" do
    test "requests while down end :link_down at once; the link reconnects", ctx do
      # the next dial waits a second: the request below is made while there is no connection,
      # however slow the machine (a dial 10 ms later beat it on a loaded one)
      {link, peer} = connected(ctx, backoff_min: 1_000, backoff_max: 1_000)
      DNCPeer.close(peer)
      assert_receive {:dnc, ^link, :disconnected}, 5_000
      assert {:error, %LinkError{reason: :link_down}} = DNC.request(link, @sns, [])
      {:ok, peer} = DNCPeer.accept(ctx.listener)
      assert_receive {:dnc, ^link, :connected}, 5_000
      task = request(link, @sns, [])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert Task.await(task) == {:ok, []}
    end

    test "the connection lost mid-transfer ends the request :link_down", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, ["N10\n"])
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.close(peer)
      assert {:error, %LinkError{reason: :link_down}} = Task.await(task)
      assert_receive {:dnc, ^link, :disconnected}, 5_000
    end

    test "a second request waits until the first transmission is over", ctx do
      {link, peer} = connected(ctx)
      first = request(link, @sns, [])
      expect(peer, @enq)
      second = request(link, @rnl, [])
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert Task.await(first) == {:ok, []}
      expect(peer, @enq)
      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @rnl_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      DNCPeer.send_raw(peer, @enq_del)
      expect(peer, @ack0)
      DNCPeer.send_raw(peer, @eot_del)
      assert Task.await(second) == {:ok, []}
    end

    test "the request's own deadline ends it :timeout with EOT", ctx do
      {link, peer} = connected(ctx)
      task = request(link, @sns, [], 100)
      expect(peer, @enq)
      expect(peer, @eot)
      assert {:error, %LinkError{reason: :timeout}} = Task.await(task)
      assert DNC.info(link).state == :idle
    end

    test "the deadline counts from the call: one that passes while the line is busy is never bid for",
         ctx do
      {link, peer} = connected(ctx)
      first = request(link, @sns, [])
      expect(peer, @enq)
      # the second waits (postponed) behind the first, and its time runs out meanwhile
      second = request(link, @sns, [], 50)
      assert {:error, %LinkError{reason: :timeout}} = Task.await(second)

      DNCPeer.send_raw(peer, @ack0)
      expect(peer, @sns_bytes)
      DNCPeer.send_raw(peer, @ack1)
      expect(peer, @eot)
      assert Task.await(first) == {:ok, []}
      # nothing more: the second was dropped once the line was free, not bid for
      assert DNCPeer.quiet?(peer, 200)
      assert DNC.info(link).state == :idle
    end
  end

  describe "options" do
    test "an unknown option or a bad value is refused at start, naming it" do
      assert_raise Vws.Options.Error, ~r/unknown DNC link option :reply_timout/, fn ->
        DNC.start_link(reply_timout: 100)
      end

      for {key, _} = bad <- [role: :master, max_naks: -1, reply_timeout: 0, endpoint: "ftp://x"] do
        error = assert_raise Vws.Options.Error, fn -> DNC.start_link([bad]) end
        assert error.key == key and error.reason == :invalid
      end
    end
  end
end
