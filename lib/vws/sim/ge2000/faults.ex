defmodule Vws.Sim.GE2000.Faults do
  @moduledoc """
  The simulated GE-2000's misbehaviour on its DNC line (`Vws.Sim.GE2000.set_fault/2`): a tap the
  simulator puts between its link's protocol and the wire (`Vws.Links.DNC.set_tap/2`), which changes
  what goes out and what comes in. The protocol itself (`Vws.Links.DNC.Session`) knows of no fault.

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

  @doc "The tap for `Vws.Links.DNC.set_tap/2`: `{#{inspect(__MODULE__)}, state}`."
  @spec tap(fault) :: {module, map}
  def tap(fault), do: {__MODULE__, %{fault: fault, done: 0, corrupted: nil}}

  @doc "The fault, as `Vws.Links.DNC.info/1` shows it."
  @spec describe(map) :: term
  def describe(%{fault: {:bid_contention, _blocks}}), do: :bid_contention
  def describe(%{fault: fault}), do: fault

  @doc false
  def outgoing(%{fault: :silent} = st, _bytes, _transfer), do: {st, []}

  def outgoing(%{fault: fault} = st, bytes, transfer)
      when bytes in [@ack0, @ack1] and fault in [:nak_once_per_block, :drop_replies] do
    case transfer do
      # the first reply to block n (a copy's is the same acknowledgement and passes)
      %{direction: :in, blocks: n} when n > st.done ->
        {%{st | done: n}, if(fault == :nak_once_per_block, do: @nak, else: [])}

      %{direction: :in, blocks: n} ->
        {%{st | done: n}, bytes}

      _ ->
        {st, bytes}
    end
  end

  def outgoing(%{fault: {:enq_as_eot, n}} = st, bytes, %{direction: :in, blocks: n})
      when bytes in [@ack0, @ack1],
      do: {%{st | fault: :armed_enq_as_eot}, []}

  def outgoing(%{fault: {:wack, n}} = st, bytes, %{direction: :in, blocks: b})
      when bytes in [@ack0, @ack1] and n > 0 and b > 0,
      do: {%{st | fault: {:wack, n - 1}}, @wack}

  def outgoing(%{fault: :corrupt} = st, <<first, _::binary>> = bytes, _transfer)
      when first in [0x01, 0x02] and bytes != st.corrupted do
    size = byte_size(bytes) - 1
    <<head::binary-size(size), last>> = bytes
    {%{st | corrupted: bytes}, <<head::binary, Bitwise.bxor(last, 0x01)>>}
  end

  def outgoing(st, bytes, _transfer), do: {st, bytes}

  @doc false
  def incoming(%{fault: :silent} = st, _bytes, _state), do: {st, "", []}

  def incoming(%{fault: {:bid_contention, blocks}} = st, <<0x05, rest::binary>>, :idle),
    do: {%{st | fault: :none}, rest, [{:transmit, blocks}]}

  def incoming(%{fault: :armed_enq_as_eot} = st, <<0x05, rest::binary>>, _state),
    do: {%{st | fault: :none}, <<0x04, rest::binary>>, []}

  def incoming(st, bytes, _state), do: {st, bytes, []}
end
