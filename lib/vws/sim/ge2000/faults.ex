defmodule Vws.Sim.GE2000.Faults do
  @moduledoc """
  The simulated GE-2000's misbehaviour on its DNC line (`Vws.Sim.GE2000.set_fault/2`): a tap
  module (`Vws.Sim.Tap`) under the simulator's link, which changes what goes out and what comes
  in. Neither the link (`Vws.Links.DNC`) nor its protocol (`Vws.Links.DNC.Session`) knows of it.

    * `:nak_once_per_block` — the acknowledgement of every block received goes out as NAK the
      first time (the block comes again; the copy is acknowledged)
    * `:drop_replies` — the first reply to every block received is lost (the peer's ENQ gets it)
    * `{:wack, n}` — the next `n` acknowledgements of received blocks go out as WACK (busy)
    * `:corrupt` — the first copy of every block sent has its block check damaged (one bit)
    * `:silent` — nothing goes out, and what comes in is ignored (a dead peer)
    * `{:bid_contention, blocks}` — at the peer's next bid, bid at the same moment (the peer's
      ENQ is taken for our own bid meeting it) and send `blocks` unsolicited
    * `{:enq_as_eot, n}` — the acknowledgement of received block `n` is lost, and the ENQ the
      peer then asks with arrives as EOT (one bit: 0x05 → 0x04), once — X3.28 cannot tell that
      from the end of the transmission (docs/dnc-drip-feed.md "DONE means done")
  """

  @type fault ::
          :nak_once_per_block
          | :drop_replies
          | {:wack, non_neg_integer}
          | :corrupt
          | :silent
          | {:bid_contention, [binary]}
          | {:enq_as_eot, pos_integer}

  @ack0 <<0x10, ?0>>
  @ack1 <<0x10, ?1>>
  @wack <<0x10, ?;>>
  @nak <<0x15>>

  @enq <<0x05>>
  @eot <<0x04>>

  @doc """
  The state of a tap (`Vws.Sim.Tap`) that does `fault`. Besides the fault it keeps what it has
  seen of the line — the tap stands outside the link and knows only its bytes: whether a
  transmission is under way (from a bid's ENQ to its EOT, either way), and in a reception, the
  link's last acknowledgement and the number of blocks it has acknowledged (ACK0 and ACK1
  alternate: an acknowledgement unlike the last is a new block's, a copy's is the same).
  """
  @spec new(fault) :: map
  def new(fault),
    do: %{fault: fault, line: :idle, last_ack: nil, block: 0, done: 0, corrupted: nil}

  @doc "The fault, as `Vws.Sim.Tap.describe/1` shows it."
  @spec describe(map) :: term
  def describe(%{fault: {:bid_contention, _blocks}}), do: :bid_contention
  def describe(%{fault: fault}), do: fault

  @doc false
  # One send of the link (a frame or a control).
  def outgoing(st, bytes) do
    st = see_outgoing(st, bytes)
    fault_outgoing(st, bytes)
  end

  @doc false
  # One chunk received.
  def incoming(%{fault: :silent} = st, _bytes), do: {st, "", []}

  def incoming(%{fault: {:bid_contention, blocks}, line: :idle} = st, <<0x05, rest::binary>>),
    do: {%{st | fault: :none, line: :busy}, rest, [{:transmit, blocks}]}

  def incoming(%{fault: :armed_enq_as_eot} = st, <<0x05, rest::binary>>),
    do: {see_incoming(%{st | fault: :none}, @eot), <<0x04, rest::binary>>, []}

  def incoming(st, bytes), do: {see_incoming(st, bytes), bytes, []}

  # What the line is doing, from the tap's side. A bid (ENQ on an idle line) starts a
  # transmission, an EOT ends it; an acknowledgement of ours unlike the last is a new block's.
  defp see_incoming(st, bytes) do
    cond do
      st.line == :idle and String.starts_with?(bytes, @enq) ->
        %{st | line: :busy, last_ack: nil, block: 0}

      # (an EOT comes after a reply, on its own: a block's check byte may be 0x04)
      String.starts_with?(bytes, @eot) ->
        %{st | line: :idle}

      true ->
        st
    end
  end

  defp see_outgoing(st, bytes) when bytes in [@ack0, @ack1] do
    cond do
      st.last_ack == nil -> %{st | last_ack: bytes}
      st.last_ack == bytes -> st
      true -> %{st | last_ack: bytes, block: st.block + 1}
    end
  end

  defp see_outgoing(st, <<0x05, _::binary>>) when st.line == :idle,
    do: %{st | line: :busy, last_ack: nil, block: 0}

  defp see_outgoing(st, <<0x04, _::binary>>), do: %{st | line: :idle}
  defp see_outgoing(st, _bytes), do: st

  defp fault_outgoing(%{fault: :silent} = st, _bytes), do: {st, []}

  # the first reply to block n (a copy's is the same acknowledgement and passes)
  defp fault_outgoing(%{fault: fault} = st, bytes)
       when bytes in [@ack0, @ack1] and fault in [:nak_once_per_block, :drop_replies] do
    # (a reception's reply to the bid is block 0's: the count starts again)
    reply = if st.block > st.done, do: fault_reply(fault), else: bytes
    {%{st | done: st.block}, reply}
  end

  defp fault_outgoing(%{fault: {:enq_as_eot, n}, block: n} = st, bytes)
       when bytes in [@ack0, @ack1],
       do: {%{st | fault: :armed_enq_as_eot}, []}

  defp fault_outgoing(%{fault: {:wack, n}, block: b} = st, bytes)
       when bytes in [@ack0, @ack1] and n > 0 and b > 0,
       do: {%{st | fault: {:wack, n - 1}}, @wack}

  defp fault_outgoing(%{fault: :corrupt} = st, <<first, _::binary>> = bytes)
       when first in [0x01, 0x02] and bytes != st.corrupted do
    size = byte_size(bytes) - 1
    <<head::binary-size(size), last>> = bytes
    {%{st | corrupted: bytes}, <<head::binary, Bitwise.bxor(last, 0x01)>>}
  end

  defp fault_outgoing(st, bytes), do: {st, bytes}

  defp fault_reply(:nak_once_per_block), do: @nak
  defp fault_reply(:drop_replies), do: []
end
