defmodule Vws.Links.DNC.SessionTest do
  # The protocol core as a state machine without sockets: two sessions back to back over an
  # in-memory line that loses and damages bytes (Vws.Test.DNCWire), in simulated time.
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.DNC.Frame.Command
  alias Vws.Links.DNC.{LinkError, Session}
  alias Vws.Test.DNCWire

  @scs %Command{direction: :send, check: :crc, operation: :part_program, text: "000001.PRO"}
  @sce %Command{direction: :send, check: :crc, operation: :download_execute, text: "000001.PRO"}
  @rcl %Command{direction: :receive, check: :crc, operation: :status}

  defp program(n, seed) do
    for i <- 1..n, do: "N#{i * 10} G01 X#{rem(i * seed, 997)}.#{rem(i, 10)} Y-#{i}\n"
  end

  defp blocks(lines, max \\ 256),
    do: Vws.Links.DNC.Frame.split_text(IO.iodata_to_binary(lines), max)

  test "a clean line: the blocks arrive once, in order, and the request ends {:ok, []}" do
    blocks = blocks(program(60, 7))
    r = DNCWire.run(command: @scs, blocks: blocks)
    assert r.reply == {:ok, []}
    assert r.received == [{:received, @scs, blocks}]
  end

  test "an R command: the answer comes back as the request's result" do
    r = DNCWire.run(command: @rcl, blocks: [], answer: ["STATE=IDLE;PROG=000000;ALARM=0"])
    assert r.reply == {:ok, ["STATE=IDLE;PROG=000000;ALARM=0"]}
  end

  test "a dead line: the bid is tried 1 + max_enqs times, then :no_answer_to_bid" do
    r = DNCWire.run(command: @scs, blocks: ["N1\n"], damage: fn _, _, rand -> {:lost, rand} end)
    assert {:error, %LinkError{reason: :no_answer_to_bid, count: 4}} = r.reply
    assert r.received == []
  end

  test "the request is refused before anything is sent when its text cannot be sent" do
    s = Session.new(limits: DNCWire.limits()) |> Session.connected()
    assert Session.request(s, @scs, ["bad\x03text"], 0) == {:error, :invalid_text}
  end

  # Damage: every byte flipped with probability p (one random bit), every chunk lost with q.
  defp damage(p, q) do
    fn _dir, bytes, rand ->
      {x, rand} = :rand.uniform_s(rand)

      if x < q do
        {:lost, rand}
      else
        {out, rand} =
          bytes
          |> :binary.bin_to_list()
          |> Enum.map_reduce(rand, fn byte, rand ->
            {y, rand} = :rand.uniform_s(rand)

            if y < p do
              {bit, rand} = :rand.uniform_s(8, rand)
              {Bitwise.bxor(byte, Bitwise.bsl(1, bit - 1)), rand}
            else
              {byte, rand}
            end
          end)

        {:erlang.list_to_binary(out), rand}
      end
    end
  end

  test "property: over a lossy, corrupting line a transfer arrives unchanged or ends in error, never DONE with other bytes" do
    property =
      :proper.forall(
        {:proper_types.range(1, 40), :proper_types.range(1, 1_000_000),
         :proper_types.elements([0.0, 0.001, 0.005, 0.02]),
         :proper_types.elements([0.0, 0.02, 0.1]), :proper_types.elements([@scs, @sce])},
        fn {lines, seed, p, q, command} ->
          blocks = blocks(program(lines, seed), 64)
          r = DNCWire.run(command: command, blocks: blocks, damage: damage(p, q), seed: seed)

          # (X3.28's limit, PROTOCOLS.md §2: the sender's last EOT lost, the receiver times out
          # and keeps nothing while the sender is done — MONARCH's directory check finds it)
          case {r.reply, command} do
            {{:ok, []}, @scs} ->
              r.received in [[{:received, @scs, blocks}], []]

            # an E reception hands every block on as it is taken: each once, in order
            {{:ok, []}, @sce} ->
              r.blocks == blocks

            # a broken transfer: what was handed on (if anything: a sender that gave up after
            # its acknowledgements were lost ends with an EOT the receiver cannot tell from a
            # normal end, §2) is the program's beginning — no block altered, skipped or twice
            {{:error, %LinkError{}}, @scs} ->
              Enum.all?(r.received, fn
                {:received, @scs, got} -> List.starts_with?(blocks, got)
                _other -> true
              end)

            {{:error, %LinkError{}}, @sce} ->
              List.starts_with?(blocks, r.blocks)

            _ ->
              false
          end
        end
      )

    assert_property(property, 150)
  end

  describe "receiver flow control (drip feed, E)" do
    test "a machine slower than the line: WACK pauses the sender, no block skipped or repeated, the buffer never over its size" do
      blocks = blocks(program(400, 3))
      total = blocks |> Enum.map(&byte_size/1) |> Enum.sum()

      r =
        DNCWire.run(
          command: @sce,
          blocks: blocks,
          receive_buffer: 2_048,
          feed: 200,
          baud: 4800
        )

      assert r.reply == {:ok, []}
      assert r.blocks == blocks
      assert r.max_fill <= 2_048
      # the machine ran at its own rate: the whole program took at least its running time
      assert r.time_ms >= div(total * 1000, 200) - div(2_048 * 1000, 200)
    end

    test "the line faster than the machine: its buffer does not run dry once the feed has started" do
      blocks = blocks(program(300, 5))

      r =
        DNCWire.run(
          command: @sce,
          blocks: blocks,
          receive_buffer: 4_096,
          feed: 300,
          baud: 4800
        )

      assert r.reply == {:ok, []}
      assert r.blocks == blocks
      # (the last block run, the buffer empties before the EOT arrives: at most a few ms)
      assert r.starved_ms < 100
    end

    test "a WACK outside an E transmission still counts against max_wacks" do
      s = Session.new(limits: DNCWire.limits()) |> Session.connected()
      {s, _, _} = Session.request(s, @scs, ["N1\n"], 0)
      {s, _, _} = Session.handle_bytes(s, <<0x10, ?0>>, 0)

      s =
        Enum.reduce(1..3, s, fn _, s ->
          {s, _, _} = Session.handle_bytes(s, <<0x10, ?;>>, 0)
          {s, _, _} = Session.handle_timeout(s, :poll_after_wack, 0)
          s
        end)

      {_s, out, events} = Session.handle_bytes(s, <<0x10, ?;>>, 0)
      assert IO.iodata_to_binary(out) == <<0x04>>
      assert Enum.any?(events, &match?({:reply, {:error, %LinkError{reason: :wack_limit}}}, &1))
    end
  end
end
