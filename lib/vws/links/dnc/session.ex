defmodule Vws.Links.DNC.Session do
  @moduledoc """
  The DNC Level 2 protocol (PROTOCOLS.md §2) as data: one end of the line — bids, blocks,
  acknowledgements, retries, contention, turnaround — with no process, no I/O, no clock and no
  Logger. `Vws.Links.DNC.Link` (the process behind `Vws.Links.DNC`) feeds it what the transport delivered
  and the timers that fired, and carries out what it returns; a test can put two sessions back
  to back over an in-memory line instead (`test/vws/links/dnc/session_test.exs`).

  Every call returns `{session, output, events}` (Mint's shape): `output` is the bytes to send
  on the line, in order (one frame or control an element); `events` what the owner of the
  session must do or know, in order:

    * `{:state_timeout, ms, tag}` — arm the protocol's reply timer `tag` (`:bid`, `:reply`,
      `:poll_after_wack`, `:response`, `:receive`, `:answer`) and call `handle_timeout/3` with
      it when it runs out. Like a gen_statem state timeout: a change of `state/1` cancels it,
      and a new one replaces it.
    * `{:reply, result}` — the request (`request/5`) is over: `{:ok, blocks}` or
      `{:error, %Vws.Links.DNC.LinkError{}}`
    * `{:notify, message}` — for the link's owner (`Vws.Links.DNC`'s "Messages to the owner")
    * `{:telemetry, event, measurements, metadata}` — `[:vws, :dnc, event]`
    * `{:log, level, message}`
    * `:peer_alive` — a frame came from the peer (the connection works)
    * `{:transfer_end, transfer, result}` — the transfer under way is over (`transfer/1` as it
      ended; `result` `:ok` or the reason it failed)

  Times are `now`, monotonic native units, given by the caller.

  ## Receiver flow control (ours, for drip feed)

  `credit` is how many bytes of text this end can still take in a `download_execute` (`E`)
  reception (`:infinity` by default: no flow control). Each text block of such a reception uses
  its size; while less than `max_text` is left, the block is acknowledged with WACK (taken, but
  send no more yet) and an ENQ is answered WACK; once `grant/2` has given enough back, ENQ gets
  the block's acknowledgement. A sender in an `E` transmission waits out any number of WACKs
  (the machine runs the program at its own pace); in every other transmission `max_wacks` holds.
  """

  # what this core returns as {:telemetry, name, …} its process emits as [:vws, :dnc, name]
  @telemetry_prefix [:vws, :dnc]

  @doc false
  def telemetry_prefix, do: @telemetry_prefix

  alias Vws.Links.DNC.{Frame, LinkError, Pace, Transfer}
  alias Vws.Links.DNC.Frame.{Command, Text}

  @counters [
    :connections,
    :transmissions,
    :receptions,
    :blocks_sent,
    :blocks_received,
    :retransmissions,
    :naks_sent,
    :naks_received,
    :duplicates,
    :enqs_sent,
    :wacks_received,
    :contentions,
    :failures,
    :unexpected
  ]

  @type state ::
          :disconnected | :idle | :bidding | :sending | :turnaround | :receiving | :answering
  @type event ::
          {:state_timeout, non_neg_integer, atom}
          | {:reply, {:ok, [binary]} | {:error, LinkError.t()}}
          | {:notify, term}
          | {:telemetry, atom, map, map}
          | {:log, Logger.level(), String.t()}
          | :peer_alive
  @type result :: {t, [iodata], [event]}

  @type t :: %__MODULE__{}
  defstruct role: :cec,
            pad: false,
            win_contention: false,
            limits: %{},
            state: :disconnected,
            decoder: nil,
            req: nil,
            tx: nil,
            # our request's transmission, yielded to a peer whose R command we answer first: bid
            # for again once the answer is sent (or was never given)
            yielded: nil,
            rx: nil,
            turnaround: nil,
            credit: :infinity,
            receive_buffer: :infinity,
            counters: Map.new(@counters, &{&1, 0}),
            out: [],
            events: []

  @doc """
  A new session, `:disconnected`. `limits` holds the `Vws.Links.DNC` limits (`reply_timeout`,
  `max_naks`, `max_enqs`, `wack_delay`, `max_wacks`, `max_contention`, `response_timeout`,
  `receive_timeout`, `answer_timeout`, `max_text`, `max_receive`) and `receive_buffer` (the
  credit an `E` reception starts with, `:infinity` by default).
  """
  @spec new(keyword) :: t
  def new(opts) do
    role = Keyword.get(opts, :role, :cec)
    limits = Map.new(Keyword.fetch!(opts, :limits))

    %__MODULE__{
      role: role,
      pad: Keyword.get(opts, :pad, role == :ge),
      win_contention: Keyword.get(opts, :win_contention, role == :ge),
      limits: limits,
      receive_buffer: Map.get(limits, :receive_buffer, :infinity)
    }
  end

  @doc "The protocol state."
  @spec state(t) :: state
  def state(%__MODULE__{state: state}), do: state

  @doc "The counters (`Vws.Links.DNC.info/1`)."
  @spec counters(t) :: map
  def counters(%__MODULE__{counters: c}), do: c

  @doc "A connection is up: the session is `:idle`, with a fresh decoder."
  @spec connected(t) :: t
  def connected(s) do
    s = bump(s, :connections)
    %{s | state: :idle, decoder: Frame.new(max_text: s.limits.max_text)}
  end

  @doc "The connection is gone: whatever was in progress ends `:link_down`."
  @spec disconnected(t, integer) :: result
  def disconnected(s, now) do
    s = if s.req || s.tx || s.rx, do: fail(s, :link_down, nil, nil, now), else: s

    done(%{
      s
      | state: :disconnected,
        decoder: nil,
        req: nil,
        tx: nil,
        yielded: nil,
        rx: nil,
        turnaround: nil
    })
  end

  @doc "Counts something the owner found unexpected (an unknown call, say)."
  @spec unexpected(t) :: t
  def unexpected(s), do: bump(s, :unexpected)

  @doc """
  Starts a request as master (only while `:idle`): bids for the line. Returns
  `{:error, :invalid_text}` for text that cannot be sent, before anything goes on the line.
  """
  @spec request(t, Command.t(), [binary], integer) :: result | {:error, :invalid_text}
  def request(%{state: :idle} = s, command, blocks, now) do
    case encode_request(command, blocks, s) do
      {:ok, frames} ->
        tx = Transfer.new_tx(:request, frames, [0 | sizes(blocks)], now)
        s = %{s | req: %{command: command, started: now}, tx: tx}
        s |> bid() |> done()

      :error ->
        {:error, :invalid_text}
    end
  end

  @doc "Bids and sends `blocks` as text without a command (only while `:idle`)."
  @spec transmit(t, [binary], integer) :: result | {:error, :invalid_text}
  def transmit(%{state: :idle} = s, blocks, now) do
    case encode_texts_safe(blocks, :lrc, s) do
      {:ok, frames} ->
        %{s | tx: Transfer.new_tx(:unsolicited, frames, sizes(blocks), now)} |> bid() |> done()

      :error ->
        {:error, :invalid_text}
    end
  end

  @doc """
  The answer to the peer's `R` command announced as `{:request, ref, command, blocks}`: bids and
  sends `blocks`. `{:error, :not_asked}` unless this end is `:answering` that `ref`.
  """
  @spec answer(t, reference, [binary], integer) :: result | {:error, :not_asked | :invalid_text}
  def answer(%{state: :answering, rx: %{ref: ref, command: command}} = s, ref, blocks, now) do
    case encode_texts_safe(blocks, command.check, s) do
      {:ok, frames} ->
        # (the answer's progress names the peer's command: the program it asked for)
        tx = Map.put(Transfer.new_tx(:answer, frames, sizes(blocks), now), :command, command)

        %{s | rx: nil, tx: tx, yielded: s.tx}
        |> bid()
        |> done()

      :error ->
        {:error, :invalid_text}
    end
  end

  def answer(_s, _ref, _blocks, _now), do: {:error, :not_asked}

  @doc "Gives `bytes` of credit back to an `E` reception (see the moduledoc)."
  @spec grant(t, non_neg_integer) :: t
  def grant(%{credit: :infinity} = s, _bytes), do: s
  def grant(s, bytes), do: %{s | credit: s.credit + bytes}

  @doc "The credit left in the `E` reception under way (`:infinity` without flow control)."
  @spec credit(t) :: non_neg_integer | :infinity
  def credit(s), do: s.credit

  @doc "Bytes from the transport."
  @spec handle_bytes(t, binary, integer) :: result
  def handle_bytes(%{decoder: nil} = s, _bytes, _now), do: done(s)

  def handle_bytes(s, bytes, now) do
    {frames, decoder} = Frame.feed(s.decoder, bytes)
    s = %{s | decoder: decoder}

    s = if Enum.any?(frames, &(not match?({:error, _}, &1))), do: event(s, :peer_alive), else: s

    frames
    |> Enum.reduce(s, fn
      {:error, error}, s -> line_error(s.state, error, s, now)
      frame, s -> frame(s.state, frame, s, now)
    end)
    |> done()
  end

  @doc "A timer armed by `{:state_timeout, ms, tag}` ran out; `:request` — the caller's deadline."
  @spec handle_timeout(t, atom, integer) :: result
  def handle_timeout(s, :request, now) do
    if s.req do
      s = if s.state in [:bidding, :sending], do: send_control(s, :eot), else: s
      block = s.tx && s.tx.acked + 1
      s = fail(s, :timeout, block, nil, now)
      done(%{s | state: :idle, rx: nil, turnaround: nil})
    else
      done(s)
    end
  end

  def handle_timeout(s, tag, now), do: timeout(s.state, tag, s, now) |> done()

  @doc "The transfer under way (`Vws.Links.DNC.Transfer.view/3`), or nil."
  @spec transfer(t) :: Transfer.view() | nil
  def transfer(s),
    do: Transfer.view(s.tx, s.rx, (s.req && s.req.command) || (s.tx && s.tx[:command]))

  ## Frames, by state

  # :idle — nobody transmitting: the peer's bid
  defp frame(:idle, :enq, s, now), do: start_receiving(s, :slave, now)

  # :bidding — our ENQ sent, waiting for ACK0
  defp frame(:bidding, :ack0, s, now) do
    s = %{s | tx: %{s.tx | bids: 0}}
    send_next(s, now)
  end

  defp frame(:bidding, :enq, %{win_contention: true} = s, _now) do
    s = log(s, :info, "DNC bid contention: the peer's ENQ meets ours; we keep the line")
    bump(s, :contentions)
  end

  defp frame(:bidding, :enq, s, now) do
    s = bump(s, :contentions)
    tx = s.tx
    yields = tx.yields + 1

    if yields > s.limits.max_contention do
      s = fail(s, :contention, nil, yields, now)
      start_receiving(s, :slave, now)
    else
      s = log(s, :info, "DNC bid contention: yielding to the peer, bidding again after its EOT")
      s = %{s | tx: %{tx | yields: yields, bids: 0}}
      start_receiving(s, :slave, now)
    end
  end

  # An answer to our bid other than ACK0 — the acknowledgement of a block, or WACK — comes from
  # a peer still receiving: our last transmission's closing EOT was lost on the line, and it
  # waits for it (X3.28 has no acknowledgement of EOT). The EOT is sent again, which ends that
  # reception as it would have ended, and we bid again. (An ACK0 damaged into ACK1 ends the
  # peer's empty reception, which hands nothing on.)
  defp frame(:bidding, reply, %{tx: tx} = s, now) when reply in [:ack1, :wack] do
    if tx.bids > s.limits.max_enqs do
      s = send_control(s, :eot)
      %{fail(s, :no_answer_to_bid, nil, tx.bids, now) | state: :idle}
    else
      s = log(s, :info, "DNC: the peer answered our bid #{reply}: it still receives; EOT again")
      s = retry(s, :eot_again, nil)
      s = send_control(s, :eot)
      bid(s)
    end
  end

  # :sending — a block sent, waiting for its acknowledgement
  defp frame(:sending, ack, %{tx: tx} = s, now) when ack in [:ack0, :ack1] do
    block = tx.acked + 1

    cond do
      # The answer to our ENQ says the block arrived. ACK0 and ACK1 differ in one bit and carry
      # no check, so one flip turns "the last block again" into "this one": heard once, the
      # sender would skip a block the receiver never took, and every block after it would
      # alternate right. Such an answer is asked for again, and counts only when the same
      # acknowledgement comes twice (bench/property_seeds.exs found the single flip). After a
      # WACK the block has arrived (WACK is a positive acknowledgement), so no second answer is
      # needed there.
      ack == expected_ack(block) and tx.polled and not tx.wacked and tx.confirm != ack ->
        confirm(s, ack, now)

      ack == expected_ack(block) ->
        text = tx.text_acked + elem(tx.sizes, block - 1)
        sent = tx.bytes_acked + IO.iodata_length(elem(tx.frames, block - 1))
        # room again after a WACK: what the machine ran since the last time (Pace)
        pace = if tx.wacked, do: Pace.released(tx.pace, ms(now), text), else: tx.pace

        tx = %{
          tx
          | acked: block,
            text_acked: text,
            bytes_acked: sent,
            naks: 0,
            enqs: 0,
            wacks: 0,
            polled: false,
            confirm: nil,
            wacked: false,
            pace: pace
        }

        send_next(%{s | tx: tx}, now)

      tx.polled ->
        # the reply to our ENQ repeats the previous acknowledgement: the block never arrived
        retransmit(%{s | tx: %{tx | confirm: nil}}, now)

      true ->
        # wrong parity out of the blue: a lost reply; ask for it again
        poll(s, :lost_reply, now)
    end
  end

  defp frame(:sending, :nak, s, now) do
    s = bump(s, :naks_received)
    s = retry(s, :nak_received, s.tx.acked + 1)
    retransmit(s, now)
  end

  defp frame(:sending, :wack, %{tx: tx} = s, now) do
    s = bump(s, :wacks_received)
    wacks = tx.wacks + 1
    # the receiver took the block and asks us to wait: a pause, not a retry (issue 25)
    s = %{s | tx: %{s.tx | pauses: s.tx.pauses + 1}}
    s = telemetry(s, :pause, %{kind: :wack_received, block: tx.acked + 1})

    if wacks > s.limits.max_wacks and not drip_feed?(s) do
      s = send_control(s, :eot)
      %{fail(s, :wack_limit, tx.acked + 1, wacks, now) | state: :idle}
    else
      {tx, ms} = pause(s, %{s.tx | wacks: wacks, wacked: true}, tx.wacked)
      state_timeout(%{s | tx: tx}, ms, :poll_after_wack)
    end
  end

  defp frame(:sending, :eot, s, now),
    do: %{fail(s, :aborted, s.tx.acked + 1, nil, now) | state: :idle}

  # :turnaround — our R command sent and EOT given; waiting for the peer to bid
  defp frame(:turnaround, :enq, s, now), do: start_receiving(%{s | turnaround: nil}, :reply, now)

  # :receiving — the peer is master; we acknowledge its blocks ACK1, ACK0, …
  #
  # A block counts once. Blocks carry no number, so what makes a copy recognisable is the
  # alternation: the sender sends a block again only when it did not see that block's ACK (or
  # saw a NAK), so a copy of the block just accepted is answered with that block's ACK again —
  # the one the sender is waiting for — and dropped. A NAK of ours asks for the block after the
  # last accepted one: whatever comes back replaces nothing. See duplicate?/2.
  defp frame(:receiving, block, %{rx: rx} = s, now)
       when is_struct(block, Command) or is_struct(block, Text) do
    if duplicate?(rx, block), do: discard_duplicate(s), else: take_block(block, s, now)
  end

  defp frame(:receiving, :enq, s, _now) do
    # "repeat your reply" — WACK while an E reception has no room for another block
    reply = if s.rx.last != :nak and short_of_credit?(s), do: :wack, else: s.rx.last
    s = send_control(%{s | rx: %{s.rx | sent: reply}}, reply)
    receive_timer(s)
  end

  defp frame(:receiving, :eot, s, now), do: end_reception(s, now)

  # :answering — the peer's R command received; the owner prepares the answer
  defp frame(:answering, :enq, s, now) do
    s = log(s, :warning, "DNC: the peer bids again before we answered its R command")
    start_receiving(%{s | rx: nil}, :slave, now)
  end

  defp frame(state, frame, s, _now) do
    s = log(s, :debug, "DNC: #{inspect(frame, limit: 5)} unexpected in state #{state}; ignored")
    bump(s, :unexpected)
  end

  defp line_error(:receiving, %{reason: reason}, s, _now)
       when reason in [:bad_bcc, :malformed, :too_long],
       do: reply_nak(s)

  defp line_error(state, error, s, _now) do
    s = log(s, :debug, "DNC: #{Exception.message(error)} (state #{state})")
    bump(s, :unexpected)
  end

  ## Timers, by state

  defp timeout(:bidding, :bid, s, now) do
    tx = s.tx

    if tx.bids > s.limits.max_enqs do
      s = send_control(s, :eot)
      %{fail(s, :no_answer_to_bid, nil, tx.bids, now) | state: :idle}
    else
      bid(s)
    end
  end

  defp timeout(:sending, :poll_after_wack, s, _now) do
    s = send_control(s, :enq)
    s = %{bump(s, :enqs_sent) | tx: %{s.tx | polled: true}}
    state_timeout(s, s.limits.reply_timeout, :reply)
  end

  defp timeout(:sending, :reply, s, now), do: poll(s, :no_reply, now)

  # No bid within `reply_timeout`: our EOT may have been lost on the line, and the peer waits
  # for it to take the line. EOT again (at most `max_enqs` times; an EOT turns nothing round
  # twice for a peer that did get the first), until `response_timeout` from the first.
  defp timeout(:turnaround, :response, %{turnaround: t} = s, now) do
    cond do
      now >= t.deadline ->
        %{fail(%{s | turnaround: nil}, :no_response, nil, nil, now) | state: :idle}

      t.eots < s.limits.max_enqs ->
        s = send_control(s, :eot)
        s = retry(s, :eot_again, nil)
        s = %{s | turnaround: %{t | eots: t.eots + 1}}
        state_timeout(s, turnaround_wait(s, now), :response)

      true ->
        state_timeout(s, turnaround_wait(s, now), :response)
    end
  end

  defp timeout(:receiving, :receive, s, now) do
    count = s.rx.count
    # an E reception's blocks were handed on as they came: its owner learns it broke off
    s = if streamed?(s.rx), do: notify(s, {:aborted, s.rx.command, []}), else: s
    s = fail(s, :receive_timeout, nil, count, now)
    %{s | state: :idle, rx: nil, credit: :infinity}
  end

  defp timeout(:answering, :answer, s, _now) do
    s = log(s, :warning, "DNC: no answer to the peer's R command from the owner in time")
    # a request of ours that yielded to that peer still has the line's next turn
    after_slave(%{s | rx: nil})
  end

  defp timeout(state, tag, s, _now) do
    s = log(s, :debug, "DNC: timer #{inspect(tag)} unexpected in state #{state}")
    bump(s, :unexpected)
  end

  defp turnaround_wait(%{turnaround: t, limits: limits}, now),
    do: max(min(limits.reply_timeout, ms(t.deadline - now)), 0)

  ## Transmitting

  defp sizes(blocks), do: Enum.map(blocks, &byte_size/1)

  defp encode_request(%Command{} = command, blocks, s) when is_list(blocks) do
    command_frame = Frame.encode(command, max_text: s.limits.max_text)

    case encode_texts_safe(blocks, command.check, s) do
      {:ok, texts} -> {:ok, [command_frame | texts]}
      :error -> :error
    end
  rescue
    ArgumentError -> :error
  end

  defp encode_request(_command, _blocks, _s), do: :error

  # Two equal blocks in a row are refused before anything goes on the line: the receiver takes
  # the second for a copy of the first (duplicate?/2). Frame.split_text/2 never makes them.
  defp encode_texts_safe(blocks, check, s) when is_list(blocks) do
    if Enum.any?(Enum.chunk_every(blocks, 2, 1, :discard), fn [a, b] -> a == b end) do
      :error
    else
      {:ok,
       for(
         text <- blocks,
         do: Frame.encode(%Text{text: text}, check: check, max_text: s.limits.max_text)
       )}
    end
  rescue
    ArgumentError -> :error
  end

  defp encode_texts_safe(_blocks, _check, _s), do: :error

  defp bid(s) do
    s = send_control(s, :enq)
    s = %{bump(s, :enqs_sent) | tx: %{s.tx | bids: s.tx.bids + 1}, state: :bidding}
    state_timeout(s, s.limits.reply_timeout, :bid)
  end

  # After ACK0 to the bid, or the right acknowledgement: the next block, or EOT after the last.
  defp send_next(%{tx: tx} = s, now) do
    if tx.acked == tuple_size(tx.frames) do
      s = send_control(s, :eot)
      finish_tx(s, now)
    else
      transmit_block(s, false)
    end
  end

  defp transmit_block(%{tx: tx} = s, retransmission?) do
    block = tx.acked + 1
    frame = elem(tx.frames, block - 1)
    s = send_bytes(s, frame)
    s = bump(s, :blocks_sent)
    s = if retransmission?, do: bump(s, :retransmissions), else: s

    s =
      telemetry(s, :block_sent, %{block: block, retransmission: retransmission?}, %{
        bytes: IO.iodata_length(frame)
      })

    state_timeout(%{s | state: :sending}, s.limits.reply_timeout, :reply)
  end

  defp retransmit(%{tx: tx} = s, now) do
    naks = tx.naks + 1

    if naks > s.limits.max_naks do
      s = send_control(s, :eot)
      %{fail(s, :nak_limit, tx.acked + 1, naks, now) | state: :idle}
    else
      transmit_block(%{s | tx: %{tx | naks: naks, polled: false}}, true)
    end
  end

  # an acknowledgement heard once in answer to our ENQ: ENQ again, and take it when it comes again
  defp confirm(%{tx: tx} = s, ack, now) do
    poll(%{s | tx: %{tx | confirm: ack}}, :confirm_ack, now)
  end

  defp poll(%{tx: tx} = s, why, now) do
    enqs = tx.enqs + 1

    if enqs > s.limits.max_enqs do
      s = send_control(s, :eot)
      %{fail(s, :no_reply, tx.acked + 1, tx.enqs, now) | state: :idle}
    else
      s = retry(s, why, tx.acked + 1)
      s = send_control(s, :enq)
      s = %{bump(s, :enqs_sent) | tx: %{s.tx | enqs: enqs, polled: true}}
      state_timeout(s, s.limits.reply_timeout, :reply)
    end
  end

  defp expected_ack(block) when rem(block, 2) == 1, do: :ack1
  defp expected_ack(_block), do: :ack0

  defp drip_feed?(%{req: %{command: %Command{operation: :download_execute}}}), do: true
  defp drip_feed?(_s), do: false

  # After a WACK, ENQ at the machine's pace in a drip feed (Pace), else after wack_delay.
  defp pause(s, tx, again?) do
    if drip_feed?(s) do
      {pace, ms} = Pace.wait(tx.pace, again?, s.limits)
      {%{tx | pace: pace}, ms}
    else
      {tx, s.limits.wack_delay}
    end
  end

  # Our EOT is sent: a request of direction S is done; one of direction R turns the line round.
  defp finish_tx(%{tx: tx} = s, now) do
    s = transfer_end(s, :ok)
    s = bump(s, :transmissions)
    s = telemetry_transmission(s, :ok, now)

    case {tx.kind, s.req} do
      {:request, %{command: %Command{direction: :receive, check: check}}} ->
        decoder = Frame.set_check(s.decoder, check)
        s = %{s | tx: nil, decoder: decoder, state: :turnaround}
        # (the state's entry: EOT again until the peer bids, within response_timeout)
        deadline = now + native_ms(s.limits.response_timeout)
        s = %{s | turnaround: %{deadline: deadline, eots: 0}}
        state_timeout(s, turnaround_wait(s, now), :response)

      {:request, _req} ->
        reply(%{s | tx: nil}, {:ok, []})

      {:answer, _} ->
        # a request of ours that yielded the line to that peer is bid for again
        after_slave(%{s | tx: s.yielded, yielded: nil})

      {_unsolicited, _} ->
        %{s | tx: nil, state: :idle}
    end
  end

  ## Receiving

  defp start_receiving(s, kind, now) do
    s = send_control(s, :ack0)
    receive_timer(%{s | rx: Transfer.new_rx(kind, now), state: :receiving, credit: :infinity})
  end

  defp receive_timer(s), do: state_timeout(s, s.limits.receive_timeout, :receive)

  defp accept_block(%{rx: rx} = s, block, size) do
    index = rx.count + 1
    ack = expected_ack(index)

    rx =
      case block do
        %Command{} -> %{rx | command: block}
        text -> %{rx | blocks: if(streamed?(rx), do: rx.blocks, else: [text | rx.blocks])}
      end

    rx = %{
      rx
      | count: index,
        bytes: rx.bytes + size,
        last: ack,
        accepted: block_frame(block),
        ack: ack
    }

    s = bump(%{s | rx: rx}, :blocks_received)
    s = telemetry(s, :block_received, %{block: index}, %{bytes: size})
    s = flow(s, block)

    # an E reception streams: every text block goes to the owner as it is taken
    s =
      case block do
        text when is_binary(text) ->
          if streamed?(rx), do: notify(s, {:block, rx.command, index, text}), else: s

        %Command{} ->
          s
      end

    reply = if is_binary(block) and short_of_credit?(s), do: :wack, else: ack
    s = send_control(%{s | rx: %{s.rx | sent: reply}}, reply)
    receive_timer(s)
  end

  defp streamed?(%{command: %Command{operation: :download_execute}}), do: true
  defp streamed?(_rx), do: false

  # An E command opens the credit; each of its text blocks uses some.
  defp flow(s, %Command{operation: :download_execute}), do: %{s | credit: s.receive_buffer}
  defp flow(%{credit: :infinity} = s, _block), do: s
  defp flow(s, text) when is_binary(text), do: %{s | credit: s.credit - byte_size(text)}
  defp flow(s, _block), do: s

  defp short_of_credit?(%{credit: :infinity}), do: false
  defp short_of_credit?(s), do: s.credit < s.limits.max_text

  defp take_block(%Command{} = command, %{rx: %{command: nil, count: 0}} = s, _now),
    do: accept_block(s, command, 0)

  # A command block in a transmission that has had one is a new transmission: the sender has
  # bid again (our last acknowledgement answering its ENQ), so the EOT that ended the one before
  # was lost on the line. That one ends here as the EOT would have ended it (whole after an
  # acknowledgement, given up after a NAK or WACK), and the new one begins with this block.
  # Blocks are checked (LRC or CRC), and a sender sends a command block only first, after ACK0.
  defp take_block(%Command{} = command, %{rx: %{kind: :slave}, tx: nil} = s, now) do
    s = log(s, :info, "DNC: a new command block while receiving: the peer's last EOT was lost")
    s = end_reception(s, now)
    s = %{s | rx: Transfer.new_rx(:slave, now), state: :receiving, credit: :infinity}
    accept_block(s, command, 0)
  end

  defp take_block(%Command{}, s, _now) do
    s = log(s, :warning, "DNC: a second command block in one transmission; answered NAK")
    reply_nak(s)
  end

  defp take_block(%Text{text: text}, %{rx: rx} = s, now) do
    if rx.bytes + byte_size(text) > s.limits.max_receive and not streamed?(rx) do
      # receiver interrupt (X3.28): EOT instead of an acknowledgement
      s = send_control(s, :eot)
      s = fail(s, :too_large, rx.count + 1, s.limits.max_receive, now)
      %{s | state: :idle, rx: nil, credit: :infinity}
    else
      accept_block(s, text, byte_size(text))
    end
  end

  defp block_frame(%Command{} = command), do: command
  defp block_frame(text) when is_binary(text), do: %Text{text: text}

  # A block equal to the last one accepted is a copy of it, always: the sender sends a block
  # again when it did not see our ACK (lost, or misread as the other parity), when a NAK of ours
  # or a damaged ACK read as one asked for it — and damaged replies can ask any number of times.
  # Blocks are not numbered, so a new block that merely repeats the last one's text would look
  # the same; no sender of ours sends two equal blocks in a row (Frame.split_text/2, and
  # request/4 refuses them), and a foreign sender that does is answered as if it sent a copy
  # until it gives up: the transfer ends ERROR, nothing taken twice. Until 2026-11-27 only as
  # many copies as NAKs were expected, and two damaged replies in a drip feed made the machine
  # run a block twice (test/vws/reliability/dnc_bit_flip_test.exs).
  defp duplicate?(%{accepted: nil}, _block), do: false
  defp duplicate?(%{accepted: accepted}, block), do: accepted == block

  defp discard_duplicate(%{rx: rx} = s) do
    s = log(s, :info, "DNC: block #{rx.count} received again; acknowledged again and dropped")
    reply = if short_of_credit?(s) and is_struct(rx.accepted, Text), do: :wack, else: rx.ack
    rx = %{rx | last: rx.ack, sent: reply}
    s = bump(%{s | rx: rx}, :duplicates)
    s = retry(s, :duplicate_received, rx.count)
    s = send_control(s, reply)
    receive_timer(s)
  end

  defp reply_nak(s) do
    s = send_control(s, :nak)
    rx = %{s.rx | last: :nak, sent: :nak}
    s = bump(%{s | rx: rx}, :naks_sent)
    s = retry(s, :nak_sent, s.rx.count + 1)
    receive_timer(s)
  end

  # EOT right after our NAK or WACK: the sender gave up (a working sender never ends there), so
  # what arrived is not a whole transmission and is never handed on as one. (An E reception
  # whose sender stops after a WACK of flow control gave up too.)
  defp end_reception(%{rx: %{sent: sent} = rx} = s, now) when sent in [:nak, :wack] do
    s = transfer_end(s, :aborted)
    blocks = Enum.reverse(rx.blocks)
    s = log(s, :warning, "DNC: the peer gave up its transmission after #{rx.count} blocks")
    s = %{s | credit: :infinity}

    case rx.kind do
      :reply ->
        %{fail(s, :aborted, rx.count + 1, nil, now) | rx: nil, state: :idle}

      :slave ->
        s = notify(s, {:aborted, rx.command, blocks})
        after_slave(%{s | rx: nil})
    end
  end

  # a bid answered and then EOT: nothing was sent (our ACK0 the peer misread, see :bidding)
  defp end_reception(%{rx: %{kind: :slave, count: 0}} = s, _now), do: after_slave(%{s | rx: nil})

  defp end_reception(%{rx: rx} = s, now) do
    s = transfer_end(s, :ok)
    blocks = Enum.reverse(rx.blocks)
    s = bump(%{s | credit: :infinity}, :receptions)

    s =
      telemetry(s, :transmission, %{direction: :in, result: :ok}, %{
        duration: now - rx.started,
        blocks: rx.count,
        bytes: rx.bytes
      })

    case rx.kind do
      :reply ->
        reply(%{s | rx: nil}, {:ok, blocks})

      :slave ->
        case rx.command do
          %Command{direction: :receive} = command ->
            ref = make_ref()
            s = notify(s, {:request, ref, command, blocks})
            s = %{s | rx: %{rx | ref: ref}, state: :answering}
            state_timeout(s, s.limits.answer_timeout, :answer)

          %Command{} = command ->
            s = notify(s, {:received, command, blocks})
            after_slave(%{s | rx: nil})

          nil ->
            s = notify(s, {:unsolicited, blocks})
            after_slave(%{s | rx: nil})
        end
    end
  end

  # After the peer's transmission: bid again for a request we yielded, or rest.
  defp after_slave(%{tx: nil} = s), do: %{s | state: :idle}
  defp after_slave(s), do: bid(s)

  ## Endings

  # Ends what is in progress with an error: the caller gets it, the owner is told, all is logged.
  defp fail(s, reason, block, count, now) do
    s = transfer_end(s, reason)
    error = %LinkError{reason: reason, block: block, count: count}
    s = log(s, :warning, "DNC transmission failed: " <> Exception.message(error))
    s = bump(s, :failures)
    s = telemetry_transmission(s, reason, now)

    s =
      case s.req do
        nil ->
          if s.tx && s.tx.kind == :answer, do: notify(s, {:answer_failed, error}), else: s

        _req ->
          %{event(s, {:reply, {:error, error}}) | req: nil}
      end

    %{s | tx: nil, yielded: nil}
  end

  defp reply(s, result), do: %{event(s, {:reply, result}) | req: nil, state: :idle}

  ## Effects

  # The GE-2000 follows its ENQ and EOT with DEL (seed §3.2); `pad` makes this end do the same.
  defp send_control(s, control) do
    pad = s.pad and control in [:enq, :eot]
    send_bytes(s, Frame.encode(control, pad: pad))
  end

  defp send_bytes(s, bytes), do: %{s | out: [bytes | s.out]}

  defp state_timeout(s, ms, tag), do: event(s, {:state_timeout, ms, tag})

  defp notify(s, msg), do: event(s, {:notify, msg})

  defp log(s, level, message), do: event(s, {:log, level, message})

  defp telemetry(s, name, metadata, measurements \\ %{count: 1}),
    do: event(s, {:telemetry, name, measurements, metadata})

  # a retry of the transfer under way: counted for its progress, and told
  defp retry(s, kind, block) do
    s =
      cond do
        s.tx -> %{s | tx: %{s.tx | retries: s.tx.retries + 1}}
        s.rx -> %{s | rx: %{s.rx | retries: s.rx.retries + 1}}
        true -> s
      end

    telemetry(s, :retry, %{kind: kind, block: block})
  end

  defp telemetry_transmission(%{tx: nil} = s, _result, _now), do: s

  defp telemetry_transmission(%{tx: tx} = s, result, now) do
    telemetry(s, :transmission, %{direction: :out, kind: tx.kind, result: result}, %{
      duration: now - tx.started,
      blocks: tuple_size(tx.frames),
      bytes: tx.bytes
    })
  end

  # the transfer under way ends (told once, with its last figures)
  defp transfer_end(s, result) do
    case transfer(s) do
      nil -> s
      t -> event(s, {:transfer_end, t, result})
    end
  end

  defp event(s, e), do: %{s | events: [e | s.events]}

  defp bump(s, counter), do: %{s | counters: Map.update!(s.counters, counter, &(&1 + 1))}

  defp done(s) do
    {%{s | out: [], events: []}, Enum.reverse(s.out), Enum.reverse(s.events)}
  end

  defp native_ms(ms), do: System.convert_time_unit(ms, :millisecond, :native)
  defp ms(native), do: System.convert_time_unit(native, :native, :millisecond)
end
