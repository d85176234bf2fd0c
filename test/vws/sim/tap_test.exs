defmodule Vws.Sim.TapTest do
  # The tap under a simulator's link, and the GE-2000's faults it carries, which know the line
  # only from its bytes (the link, Vws.Links.DNC, knows nothing of them).
  use ExUnit.Case, async: true

  alias Vws.Links.Transport
  alias Vws.Sim.GE2000.Faults
  alias Vws.Sim.Tap

  doctest Tap

  @enq <<0x05>>
  @enq_del <<0x05, 0x7F>>
  @eot <<0x04>>
  @ack0 <<0x10, ?0>>
  @ack1 <<0x10, ?1>>
  @wack <<0x10, ?;>>
  @nak <<0x15>>
  @block <<0x02, "N10", 0x03, 0x4D>>

  # the link's sends and the chunks it receives, in order, through a Faults tap: what went out
  defp run(fault, script) do
    Enum.reduce(script, {Faults.new(fault), []}, fn
      {:in, bytes}, {st, out} ->
        {st, _bytes, _notes} = Faults.incoming(st, bytes)
        {st, out}

      {:out, bytes}, {st, out} ->
        {st, sent} = Faults.outgoing(st, bytes)
        {st, out ++ [IO.iodata_to_binary(sent)]}
    end)
    |> elem(1)
  end

  # a reception of `blocks` blocks as the GE's link answers it: the bid's ACK0, then ACK1, ACK0, …
  defp reception(blocks) do
    acks = Stream.cycle([@ack1, @ack0]) |> Enum.take(blocks)

    [{:in, @enq}, {:out, @ack0}] ++
      Enum.flat_map(acks, &[{:in, @block}, {:out, &1}]) ++ [{:in, @eot}]
  end

  test "nak_once_per_block: the first reply to each block is NAK, the copy's passes" do
    script = [
      {:in, @enq},
      {:out, @ack0},
      {:in, @block},
      {:out, @ack1},
      # the copy after the NAK: the link acknowledges it the same way
      {:in, @block},
      {:out, @ack1},
      {:in, @block},
      {:out, @ack0},
      {:in, @block},
      {:out, @ack0},
      {:in, @eot}
    ]

    assert run(:nak_once_per_block, script) == [@ack0, @nak, @ack1, @nak, @ack0]
  end

  test "each reception counts its blocks afresh (a later command block is faulted too)" do
    out = run(:nak_once_per_block, reception(2) ++ reception(1))
    assert out == [@ack0, @nak, @nak, @ack0, @nak]
  end

  test "drop_replies: the first reply to a block is lost; the one answering ENQ goes" do
    script = [
      {:in, @enq},
      {:out, @ack0},
      {:in, @block},
      {:out, @ack1},
      {:in, @enq},
      {:out, @ack1}
    ]

    assert run(:drop_replies, script) == [@ack0, "", @ack1]
  end

  test "{:wack, n}: n acknowledgements of blocks go out as WACK, never the bid's" do
    out = run({:wack, 2}, reception(3))
    assert out == [@ack0, @wack, @wack, @ack1]
  end

  test "{:enq_as_eot, n}: block n's acknowledgement is lost and the ENQ asking for it is EOT" do
    {st, []} =
      Enum.reduce(
        [{:in, @enq}, {:out, @ack0}, {:in, @block}, {:out, @ack1}, {:in, @block}],
        Faults.new({:enq_as_eot, 2}),
        fn
          {:in, b}, st -> st |> Faults.incoming(b) |> elem(0)
          {:out, b}, st -> st |> Faults.outgoing(b) |> elem(0)
        end
      )
      |> Faults.outgoing(@ack0)

    assert {_, <<0x04, 0x7F>>, []} = Faults.incoming(st, @enq_del)
  end

  test "bid_contention: the peer's bid on an idle line is taken for ours meeting it, once" do
    st = Faults.new({:bid_contention, ["STATE=IDLE"]})
    {st, rest, notes} = Faults.incoming(st, @enq)
    assert rest == "" and notes == [{:transmit, ["STATE=IDLE"]}]
    # mid-transmission an ENQ is a question, and the fault is spent anyway
    assert {_, @enq, []} = Faults.incoming(st, @enq)
  end

  test "silent and corrupt" do
    assert run(:silent, reception(1)) == ["", ""]
    {st, out} = Faults.outgoing(Faults.new(:corrupt), @block)
    assert byte_size(out) == byte_size(@block) and out != @block
    # the copy that follows goes as it is
    assert {_, @block} = Faults.outgoing(st, @block)
  end

  test "through a connection: the tap's notes reach its owner; without a tap module bytes pass" do
    endpoint = "loopback:tap-test-#{System.unique_integer([:positive])}"
    {:ok, listener} = Transport.listen(endpoint)
    {:ok, tap} = Tap.start_link(owner: self())
    {:ok, client} = Transport.connect(endpoint)
    {:ok, server} = Transport.accept(listener, 1_000)
    server = Tap.wrap(server, tap)
    assert Tap.describe(tap) == :none

    :ok = Tap.set(tap, {Faults, Faults.new({:bid_contention, ["X"]})})
    assert Tap.describe(tap) == :bid_contention
    :ok = Transport.send(client, @enq)
    :ok = Transport.activate(server)
    assert {:data, ""} = Transport.handle_message(server, receive(do: (m -> m)))
    assert_received {:tap, ^tap, {:transmit, ["X"]}}

    :ok = Tap.set(tap, nil)
    :ok = Transport.send(server, "as is")
    :ok = Transport.activate(client)
    assert {:data, "as is"} = Transport.handle_message(client, receive(do: (m -> m)))
    assert Transport.peer(server) =~ "loopback"
  end
end
