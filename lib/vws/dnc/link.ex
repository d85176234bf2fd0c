defmodule Vws.DNC.Link do
  @moduledoc false
  # The DNC Level 2 link as a gen_statem; documented in Vws.DNC (its facade).
  #
  # States:   :disconnected → :idle ⇄ :bidding → :sending → (:turnaround → :receiving) → :idle
  #                           :idle → :receiving (the peer bid) → (:answering → :bidding → :sending)
  #
  # Bytes from the transport go through Vws.DNC.Frame; every control, block and decoder error
  # re-enters as {:next_event, :internal, {:frame, f} | {:line_error, e}}, so the state clauses
  # see decoded frames only. Protocol reply timers are state_timeouts; the caller's deadline is
  # the generic timeout {:timeout, :request}. Requests that arrive while a transmission is in
  # progress are postponed until :idle; while :disconnected they are answered :link_down.

  @behaviour :gen_statem
  require Logger

  alias Vws.DNC.{Frame, LinkError}
  alias Vws.DNC.Frame.{Command, Text}
  alias Vws.Transport

  @defaults [
    role: :cec,
    owner: nil,
    endpoint: nil,
    reply_timeout: 3_000,
    max_naks: 3,
    max_enqs: 3,
    wack_delay: 2_000,
    max_wacks: 3,
    max_contention: 3,
    response_timeout: 10_000,
    receive_timeout: 10_000,
    answer_timeout: 5_000,
    max_text: 256,
    max_receive: 4 * 1024 * 1024,
    connect_timeout: 2_000,
    backoff_min: 100,
    backoff_max: 5_000,
    pace: nil,
    char_bits: 10
  ]

  @doc false
  def defaults, do: @defaults

  defstruct [
    :name,
    :owner,
    :endpoint,
    :role,
    :pad,
    :win_contention,
    :limits,
    :conn,
    :peer,
    :decoder,
    :backoff,
    :req,
    :tx,
    :rx,
    :line,
    :turnaround,
    fault: :none,
    connect_failures: 0,
    counters: %{}
  ]

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

  ## Start

  @doc false
  def start_link(opts) do
    case Keyword.get(opts, :name) do
      nil -> :gen_statem.start_link(__MODULE__, opts, [])
      name -> :gen_statem.start_link(name, __MODULE__, opts, [])
    end
  end

  @impl true
  def callback_mode, do: [:state_functions, :state_enter]

  @impl true
  def init(opts) do
    unknown = Keyword.keys(opts) -- [:name, :pad, :win_contention | Keyword.keys(@defaults)]
    if unknown != [], do: raise(ArgumentError, "unknown DNC link options #{inspect(unknown)}")

    o = Keyword.merge(@defaults, opts)
    role = o[:role]
    unless role in [:cec, :ge], do: raise(ArgumentError, "role must be :cec or :ge")

    Logger.metadata(
      dnc_link: o[:name] || self(),
      dnc_role: role,
      workstation: Vws.Names.id_of(o[:name])
    )

    pace = pace_ns(o[:pace], o[:char_bits])

    data = %__MODULE__{
      name: o[:name] || self(),
      owner: o[:owner],
      endpoint: o[:endpoint],
      role: role,
      pad: Keyword.get(o, :pad, role == :ge),
      win_contention: Keyword.get(o, :win_contention, role == :ge),
      limits: Map.new(Keyword.drop(o, [:name, :owner, :endpoint, :role, :pad, :win_contention])),
      backoff: Vws.Backoff.new(o[:backoff_min], o[:backoff_max]),
      # (monotonic time may be negative: the line is free "now", not at 0)
      line: %{
        char: pace,
        tx_free: System.monotonic_time(),
        rx_free: System.monotonic_time(),
        tx: :queue.new(),
        rx: :queue.new(),
        timers: %{},
        slack: System.convert_time_unit(1, :millisecond, :native),
        logical: nil,
        sent: nil
      },
      counters: Map.new(@counters, &{&1, 0})
    }

    {:ok, :disconnected, data}
  end

  # native time units per character on the line, or nil (no pacing)
  defp pace_ns(nil, _bits), do: nil
  defp pace_ns(false, _bits), do: nil
  defp pace_ns(baud, bits) when is_integer(baud) and baud > 0, do: div(native(1) * bits, baud)
  defp native(seconds), do: System.convert_time_unit(seconds, :second, :native)

  ## :disconnected — (re)connecting with backoff, or waiting to be given a connection

  def disconnected(:enter, _old, %{endpoint: nil}), do: :keep_state_and_data

  # The first dial goes at once; after a lost connection the back-off's next wait (it doubles
  # until the peer has sent a frame on a connection, see Vws.Backoff).
  def disconnected(:enter, _old, %{counters: %{connections: 0}, connect_failures: 0}),
    do: {:keep_state_and_data, [{:state_timeout, 0, :connect}]}

  def disconnected(:enter, _old, data) do
    {wait, backoff} = Vws.Backoff.next(data.backoff)
    {:keep_state, %{data | backoff: backoff}, [{:state_timeout, wait, :connect}]}
  end

  def disconnected(:state_timeout, :connect, data) do
    case Transport.connect(data.endpoint, timeout: data.limits.connect_timeout) do
      {:ok, conn} ->
        {:next_state, :idle, take_connection(data, conn)}

      {:error, reason} ->
        failures = data.connect_failures + 1
        level = if failures == 1, do: :warning, else: :debug
        Logger.log(level, "DNC link cannot reach #{data.endpoint}: #{inspect(reason)}; retrying")
        {wait, backoff} = Vws.Backoff.next(data.backoff)
        data = %{data | backoff: backoff, connect_failures: failures}

        emit(data, :connect_failed, %{endpoint: to_string(data.endpoint), reason: reason}, %{
          count: 1,
          retry_in: wait
        })

        {:keep_state, data, [{:state_timeout, wait, :connect}]}
    end
  end

  def disconnected({:call, from}, {:request, _cmd, _blocks, _timeout}, _data) do
    {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :link_down}}}]}
  end

  def disconnected(type, content, data), do: common(type, content, :disconnected, data)

  ## :idle — connected, nobody transmitting

  def idle(:enter, _old, _data), do: :keep_state_and_data

  def idle({:call, from}, {:request, command, blocks, timeout}, data) do
    case encode_request(command, blocks, data) do
      {:ok, frames} ->
        ref = make_ref()
        req = %{from: from, ref: ref, command: command, started: System.monotonic_time()}
        deadline = if timeout == :infinity, do: [], else: [{{:timeout, :request}, timeout, ref}]
        data = %{data | req: req, tx: new_tx(:request, frames)}
        bid(data, deadline)

      :error ->
        {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :invalid_text}}}]}
    end
  end

  def idle(:internal, {:frame, :enq}, %{fault: {:bid_contention, blocks}} = data) do
    # Simulated collision: we bid at the very moment the peer did, and (as the GE-2000) win.
    Logger.info("DNC fault: bidding over the peer's ENQ")
    data = %{data | fault: :none, tx: new_tx(:unsolicited, encode_texts(blocks, :lrc, data))}
    bid(data, [])
  end

  def idle(:internal, {:frame, :enq}, data), do: start_receiving(data, :slave)

  def idle(type, content, data), do: common(type, content, :idle, data)

  ## :bidding — our ENQ sent, waiting for ACK0

  def bidding(:enter, _old, _data), do: :keep_state_and_data

  def bidding(:internal, {:frame, :ack0}, data) do
    data = %{data | tx: %{data.tx | bids: 0}}
    send_next(data)
  end

  def bidding(:internal, {:frame, :enq}, %{win_contention: true} = data) do
    Logger.info("DNC bid contention: the peer's ENQ meets ours; we keep the line")
    {:keep_state, bump(data, :contentions)}
  end

  def bidding(:internal, {:frame, :enq}, data) do
    data = bump(data, :contentions)
    tx = data.tx
    yields = tx.yields + 1

    if yields > data.limits.max_contention do
      data = fail(data, :contention, nil, yields)
      start_receiving(data, :slave)
    else
      Logger.info("DNC bid contention: yielding to the peer, bidding again after its EOT")
      data = %{data | tx: %{tx | yields: yields, bids: 0}}
      start_receiving(data, :slave)
    end
  end

  def bidding(:state_timeout, :bid, data) do
    tx = data.tx

    if tx.bids > data.limits.max_enqs do
      data = send_control(data, :eot)
      {:next_state, :idle, fail(data, :no_answer_to_bid, nil, tx.bids)}
    else
      bid(data, [])
    end
  end

  def bidding(type, content, data), do: common(type, content, :bidding, data)

  ## :sending — a block sent, waiting for its acknowledgement

  def sending(:enter, _old, _data), do: :keep_state_and_data

  def sending(:internal, {:frame, ack}, %{tx: tx} = data) when ack in [:ack0, :ack1] do
    block = tx.acked + 1

    cond do
      ack == expected_ack(block) ->
        data = %{data | tx: %{tx | acked: block, naks: 0, enqs: 0, wacks: 0, polled: false}}
        send_next(data)

      tx.polled ->
        # the reply to our ENQ repeats the previous acknowledgement: the block never arrived
        retransmit(data)

      true ->
        # wrong parity out of the blue: a lost reply; ask for it again
        poll(data, :lost_reply)
    end
  end

  def sending(:internal, {:frame, :nak}, data) do
    data = bump(data, :naks_received)
    emit(data, :retry, %{kind: :nak_received, block: data.tx.acked + 1})
    retransmit(data)
  end

  def sending(:internal, {:frame, :wack}, %{tx: tx} = data) do
    data = bump(data, :wacks_received)
    wacks = tx.wacks + 1
    emit(data, :retry, %{kind: :wack_received, block: tx.acked + 1})

    if wacks > data.limits.max_wacks do
      data = send_control(data, :eot)
      {:next_state, :idle, fail(data, :wack_limit, tx.acked + 1, wacks)}
    else
      data = %{data | tx: %{tx | wacks: wacks}}
      {:keep_state, data, [{:state_timeout, data.limits.wack_delay, :poll_after_wack}]}
    end
  end

  def sending(:internal, {:frame, :eot}, data) do
    {:next_state, :idle, fail(data, :aborted, data.tx.acked + 1, nil)}
  end

  def sending(:state_timeout, :poll_after_wack, data) do
    data = send_control(data, :enq)
    data = %{bump(data, :enqs_sent) | tx: %{data.tx | polled: true}}
    {:keep_state, data, [{:state_timeout, data.limits.reply_timeout, :reply}]}
  end

  def sending(:state_timeout, :reply, data), do: poll(data, :no_reply)

  def sending(type, content, data), do: common(type, content, :sending, data)

  ## :turnaround — our R command sent and EOT given; waiting for the peer to bid

  # No bid within `reply_timeout`: our EOT may have been lost on the line, and the peer waits
  # for it to take the line. EOT again (at most `max_enqs` times; an EOT turns nothing round
  # twice for a peer that did get the first), until `response_timeout` from the first.
  def turnaround(:enter, _old, data) do
    deadline = now_ms() + data.limits.response_timeout
    data = %{data | turnaround: %{deadline: deadline, eots: 0}}
    {:keep_state, data, [{:state_timeout, turnaround_wait(data), :response}]}
  end

  def turnaround(:internal, {:frame, :enq}, data),
    do: start_receiving(%{data | turnaround: nil}, :reply)

  def turnaround(:state_timeout, :response, %{turnaround: t} = data) do
    cond do
      now_ms() >= t.deadline ->
        {:next_state, :idle, fail(%{data | turnaround: nil}, :no_response, nil, nil)}

      t.eots < data.limits.max_enqs ->
        data = send_control(data, :eot)
        emit(data, :retry, %{kind: :eot_again, block: nil})
        data = %{data | turnaround: %{t | eots: t.eots + 1}}
        {:keep_state, data, [{:state_timeout, turnaround_wait(data), :response}]}

      true ->
        {:keep_state_and_data, [{:state_timeout, turnaround_wait(data), :response}]}
    end
  end

  def turnaround(type, content, data), do: common(type, content, :turnaround, data)

  defp turnaround_wait(%{turnaround: t, limits: limits}),
    do: max(min(limits.reply_timeout, t.deadline - now_ms()), 0)

  defp now_ms, do: System.monotonic_time(:millisecond)

  ## :receiving — the peer is master; we acknowledge its blocks ACK1, ACK0, …
  #
  # A block counts once. Blocks carry no number, so what makes a copy recognisable is the
  # alternation: the sender sends a block again only when it did not see that block's ACK (or saw
  # a NAK), so a copy of the block just accepted is answered with that block's ACK again — the
  # one the sender is waiting for — and dropped. A NAK of ours asks for the block after the last
  # accepted one: whatever comes back replaces nothing. See duplicate?/2 for when a block equal
  # to the last one is a copy.

  def receiving(:enter, _old, _data), do: :keep_state_and_data

  def receiving(:internal, {:frame, block}, %{rx: rx} = data)
      when is_struct(block, Command) or is_struct(block, Text) do
    if duplicate?(rx, block), do: discard_duplicate(data), else: take_block(block, data)
  end

  def receiving(:internal, {:line_error, %{reason: reason}}, data)
      when reason in [:bad_bcc, :malformed, :too_long] do
    reply_nak(data)
  end

  def receiving(:internal, {:frame, :enq}, data) do
    # "repeat your reply"
    {data, reply} =
      case data.fault do
        {:wack, n} when n > 0 -> {%{data | fault: {:wack, n - 1}}, :wack}
        _ -> {data, data.rx.last}
      end

    # a NAK said again may bring one more copy of the block, like the first
    naks = if reply == :nak, do: data.rx.naks + 1, else: data.rx.naks
    data = send_control(%{data | rx: %{data.rx | sent: reply, naks: naks}}, reply)
    {:keep_state, data, [receive_timer(data)]}
  end

  def receiving(:internal, {:frame, :eot}, data), do: end_reception(data)

  def receiving(:state_timeout, :receive, data) do
    count = data.rx.count
    data = fail(data, :receive_timeout, nil, count)
    {:next_state, :idle, %{data | rx: nil}}
  end

  def receiving(type, content, data), do: common(type, content, :receiving, data)

  ## :answering — the peer's R command received; its owner prepares the answer

  def answering(:enter, _old, data),
    do: {:keep_state_and_data, [{:state_timeout, data.limits.answer_timeout, :answer}]}

  def answering(
        {:call, from},
        {:answer, ref, blocks},
        %{rx: %{ref: ref, command: command}} = data
      ) do
    case encode_texts_safe(blocks, command.check, data) do
      {:ok, frames} ->
        data = %{data | rx: nil, tx: new_tx(:answer, frames)}
        bid(data, [{:reply, from, :ok}])

      :error ->
        {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :invalid_text}}}]}
    end
  end

  def answering(:state_timeout, :answer, data) do
    Logger.warning("DNC: no answer to the peer's R command from the owner in time")
    {:next_state, :idle, %{data | rx: nil}}
  end

  def answering(:internal, {:frame, :enq}, data) do
    Logger.warning("DNC: the peer bids again before we answered its R command")
    start_receiving(%{data | rx: nil}, :slave)
  end

  def answering(type, content, data), do: common(type, content, :answering, data)

  ## Events every state handles alike

  defp common({:call, from}, :info, state, data) do
    info = %{
      state: state,
      role: data.role,
      endpoint: data.endpoint,
      peer: data.peer,
      fault: data.fault,
      max_text: data.limits.max_text,
      pace: data.limits.pace,
      counters: data.counters,
      transfer: transfer(data)
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  defp common({:call, from}, {:set_fault, fault}, _state, data) do
    {:keep_state, %{data | fault: fault}, [{:reply, from, :ok}]}
  end

  defp common({:call, from}, {:attach, conn}, _state, data) do
    data =
      if data.conn do
        Logger.warning("DNC: a new connection takes over from #{data.peer}, which is closed")
        old = data.conn
        data = lose_connection(data, :taken_over)
        Transport.close(old)
        data
      else
        data
      end

    {:next_state, :idle, take_connection(data, conn), [{:reply, from, :ok}]}
  end

  defp common({:call, _from}, {:request, _, _, _}, _state, _data),
    do: {:keep_state_and_data, [:postpone]}

  defp common({:call, from}, {:answer, _ref, _blocks}, _state, _data),
    do: {:keep_state_and_data, [{:reply, from, {:error, :not_asked}}]}

  defp common({:call, from}, other, _state, data) do
    Logger.warning("DNC: unknown call #{inspect(other, limit: 5)}")
    {:keep_state, bump(data, :unexpected), [{:reply, from, {:error, :unknown_call}}]}
  end

  defp common({:timeout, :request}, ref, state, %{req: %{ref: ref}} = data) do
    data = if state in [:bidding, :sending], do: send_control(data, :eot), else: data
    block = data.tx && data.tx.acked + 1
    data = fail(data, :timeout, block, nil)
    {:next_state, :idle, %{data | rx: nil}}
  end

  defp common({:timeout, :request}, _stale, _state, _data), do: :keep_state_and_data

  defp common(:info, {:timeout, ref, :line_tx}, _state, data) do
    if data.line.timers[:tx] == ref, do: {:keep_state, flush_tx(data)}, else: :keep_state_and_data
  end

  defp common(:info, {:timeout, ref, :line_rx}, _state, data) do
    if data.line.timers[:rx] == ref, do: flush_rx(data), else: :keep_state_and_data
  end

  defp common(:info, msg, state, %{conn: conn} = data) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        received(bytes, data)

      :closed ->
        connection_lost(state, data, :closed)

      {:error, reason} ->
        connection_lost(state, data, reason)

      :unknown ->
        Logger.debug("DNC link ignored #{inspect(msg, limit: 5)}")
        :keep_state_and_data
    end
  end

  defp common(:internal, {:frame, frame}, state, data) do
    Logger.debug("DNC: #{inspect(frame, limit: 5)} unexpected in state #{state}; ignored")
    {:keep_state, bump(data, :unexpected)}
  end

  defp common(:internal, {:line_error, error}, state, data) do
    Logger.debug("DNC: #{Exception.message(error)} (state #{state})")
    {:keep_state, bump(data, :unexpected)}
  end

  defp common(type, content, state, data) do
    Logger.debug("DNC: #{inspect({type, content}, limit: 5)} unexpected in state #{state}")
    {:keep_state, bump(data, :unexpected)}
  end

  ## Connection

  defp take_connection(data, conn) do
    :ok = Transport.activate(conn)
    peer = Transport.peer(conn)
    Logger.info("DNC link connected to #{peer}")
    emit(data, :connected, %{peer: peer})
    notify(data, :connected)

    decoder = Frame.new(max_text: data.limits.max_text)

    %{
      bump(data, :connections)
      | conn: conn,
        peer: peer,
        decoder: decoder,
        connect_failures: 0
    }
  end

  defp connection_lost(_state, data, reason) do
    Logger.warning("DNC link to #{data.peer} lost: #{inspect(reason)}")
    data = lose_connection(data, reason)
    {:next_state, :disconnected, data}
  end

  # Everything in progress ends :link_down; the connection and line queues are dropped.
  defp lose_connection(data, reason) do
    data = if data.req || data.tx || data.rx, do: fail(data, :link_down, nil, nil), else: data
    emit(data, :disconnected, %{peer: data.peer, reason: reason})
    notify(data, :disconnected)

    for {_, ref} <- data.line.timers, do: :erlang.cancel_timer(ref)
    line = %{data.line | tx: :queue.new(), rx: :queue.new(), timers: %{}}
    %{data | conn: nil, peer: nil, decoder: nil, req: nil, tx: nil, rx: nil, line: line}
  end

  ## Transmitting

  # The transmission under way, for info/1: its blocks and bytes so far and in all (a reception's
  # total is not known before its ETX), its command and its start (monotonic ms).
  defp transfer(%{tx: %{frames: frames} = tx} = data) do
    total = tuple_size(frames)

    %{
      direction: :out,
      command: data.req && data.req.command,
      blocks: tx.acked,
      total_blocks: total,
      bytes: div(tx.bytes * tx.acked, max(total, 1)),
      total_bytes: tx.bytes,
      started_ms: System.convert_time_unit(tx.started, :native, :millisecond)
    }
  end

  defp transfer(%{rx: %{} = rx} = data) do
    %{
      direction: :in,
      command: rx.command || (data.req && data.req.command),
      blocks: rx.count,
      total_blocks: nil,
      bytes: rx.bytes,
      total_bytes: nil,
      started_ms: System.convert_time_unit(rx.started, :native, :millisecond)
    }
  end

  defp transfer(_data), do: nil

  defp new_tx(kind, frames) do
    %{
      kind: kind,
      frames: List.to_tuple(frames),
      acked: 0,
      bids: 0,
      yields: 0,
      naks: 0,
      enqs: 0,
      wacks: 0,
      polled: false,
      corrupted: 0,
      started: System.monotonic_time(),
      bytes: Enum.reduce(frames, 0, &(IO.iodata_length(&1) + &2))
    }
  end

  defp encode_request(%Command{} = command, blocks, data) when is_list(blocks) do
    command_frame = Frame.encode(command, max_text: data.limits.max_text)

    case encode_texts_safe(blocks, command.check, data) do
      {:ok, texts} -> {:ok, [command_frame | texts]}
      :error -> :error
    end
  rescue
    ArgumentError -> :error
  end

  defp encode_request(_command, _blocks, _data), do: :error

  defp encode_texts_safe(blocks, check, data) when is_list(blocks) do
    {:ok, encode_texts(blocks, check, data)}
  rescue
    ArgumentError -> :error
  end

  defp encode_texts_safe(_blocks, _check, _data), do: :error

  defp encode_texts(blocks, check, data) do
    for text <- blocks,
        do: Frame.encode(%Text{text: text}, check: check, max_text: data.limits.max_text)
  end

  defp bid(data, actions) do
    data = send_control(data, :enq)
    data = %{bump(data, :enqs_sent) | tx: %{data.tx | bids: data.tx.bids + 1}}
    {:next_state, :bidding, data, [{:state_timeout, data.limits.reply_timeout, :bid} | actions]}
  end

  # After ACK0 to the bid, or the right acknowledgement: the next block, or EOT after the last.
  defp send_next(%{tx: tx} = data) do
    if tx.acked == tuple_size(tx.frames) do
      data = send_control(data, :eot)
      finish_tx(data)
    else
      transmit(data, false)
    end
  end

  defp transmit(%{tx: tx} = data, retransmission?) do
    block = tx.acked + 1
    frame = elem(tx.frames, block - 1)

    {frame, tx} =
      if data.fault == :corrupt and tx.corrupted < block do
        {corrupt(frame), %{tx | corrupted: block}}
      else
        {frame, tx}
      end

    data = send_bytes(%{data | tx: tx}, frame)
    data = bump(data, :blocks_sent)
    data = if retransmission?, do: bump(data, :retransmissions), else: data

    emit(data, :block_sent, %{block: block, retransmission: retransmission?}, %{
      bytes: IO.iodata_length(frame)
    })

    {:next_state, :sending, data, [{:state_timeout, data.limits.reply_timeout, :reply}]}
  end

  # one bit flipped in the block check: the receiver must find it and answer NAK
  defp corrupt(frame) do
    bytes = IO.iodata_to_binary(frame)
    size = byte_size(bytes) - 1
    <<head::binary-size(size), last>> = bytes
    <<head::binary, Bitwise.bxor(last, 0x01)>>
  end

  defp retransmit(%{tx: tx} = data) do
    naks = tx.naks + 1

    if naks > data.limits.max_naks do
      data = send_control(data, :eot)
      {:next_state, :idle, fail(data, :nak_limit, tx.acked + 1, naks)}
    else
      transmit(%{data | tx: %{tx | naks: naks, polled: false}}, true)
    end
  end

  defp poll(%{tx: tx} = data, why) do
    enqs = tx.enqs + 1

    if enqs > data.limits.max_enqs do
      data = send_control(data, :eot)
      {:next_state, :idle, fail(data, :no_reply, tx.acked + 1, tx.enqs)}
    else
      emit(data, :retry, %{kind: why, block: tx.acked + 1})
      data = send_control(data, :enq)
      data = %{bump(data, :enqs_sent) | tx: %{tx | enqs: enqs, polled: true}}
      {:keep_state, data, [{:state_timeout, data.limits.reply_timeout, :reply}]}
    end
  end

  defp expected_ack(block) when rem(block, 2) == 1, do: :ack1
  defp expected_ack(_block), do: :ack0

  # Our EOT is sent: a request of direction S is done; one of direction R turns the line round.
  defp finish_tx(%{tx: tx} = data) do
    data = bump(data, :transmissions)
    emit_transmission(data, :ok)

    case {tx.kind, data.req} do
      {:request, %{command: %Command{direction: :receive, check: check}}} ->
        decoder = Frame.set_check(data.decoder, check)
        {:next_state, :turnaround, %{data | tx: nil, decoder: decoder}}

      {:request, req} ->
        reply_req(%{data | tx: nil}, req, {:ok, []}, :idle)

      {_answer_or_unsolicited, _} ->
        {:next_state, :idle, %{data | tx: nil}}
    end
  end

  ## Receiving

  defp start_receiving(data, kind) do
    data = send_control(data, :ack0)

    rx = %{
      kind: kind,
      command: nil,
      blocks: [],
      count: 0,
      bytes: 0,
      last: :ack0,
      sent: :ack0,
      accepted: nil,
      ack: :ack0,
      naks: 0,
      copies: 0,
      naked: 0,
      dropped: 0,
      ref: nil,
      started: System.monotonic_time()
    }

    data = %{data | rx: rx}
    {:next_state, :receiving, data, [receive_timer(data)]}
  end

  defp receive_timer(data), do: {:state_timeout, data.limits.receive_timeout, :receive}

  defp accept_block(%{rx: rx} = data, block, size) do
    index = rx.count + 1
    ack = expected_ack(index)

    case data.fault do
      :nak_once_per_block when rx.naked < index ->
        Logger.debug("DNC fault: first copy of block #{index} answered NAK")
        reply_nak(%{data | rx: %{rx | naked: index}})

      _ ->
        rx =
          case block do
            %Command{} -> %{rx | command: block}
            text -> %{rx | blocks: [text | rx.blocks]}
          end

        # every NAK since the previous block may bring a copy of this one; so may a reply of
        # ours the sender did not see or misread: at least one copy is expected
        copies = max(rx.naks, 1)

        rx = %{
          rx
          | count: index,
            bytes: rx.bytes + size,
            last: ack,
            accepted: block_frame(block),
            ack: ack,
            naks: 0,
            copies: copies
        }

        data = bump(%{data | rx: rx}, :blocks_received)
        emit(data, :block_received, %{block: index}, %{bytes: size})

        {data, reply} =
          case data.fault do
            {:wack, n} when n > 0 -> {%{data | fault: {:wack, n - 1}}, :wack}
            :drop_replies when rx.dropped < index -> {%{data | rx: %{rx | dropped: index}}, nil}
            _ -> {data, ack}
          end

        data =
          if reply,
            do: send_control(%{data | rx: %{data.rx | sent: reply}}, reply),
            else: data

        {:keep_state, data, [receive_timer(data)]}
    end
  end

  defp take_block(%Command{} = command, %{rx: %{command: nil, count: 0}} = data),
    do: accept_block(data, command, 0)

  defp take_block(%Command{}, data) do
    Logger.warning("DNC: a second command block in one transmission; answered NAK")
    reply_nak(data)
  end

  defp take_block(%Text{text: text}, %{rx: rx} = data) do
    if rx.bytes + byte_size(text) > data.limits.max_receive do
      # receiver interrupt (X3.28): EOT instead of an acknowledgement
      data = send_control(data, :eot)
      data = fail(data, :too_large, rx.count + 1, data.limits.max_receive)
      {:next_state, :idle, %{data | rx: nil}}
    else
      accept_block(data, text, byte_size(text))
    end
  end

  defp block_frame(%Command{} = command), do: command
  defp block_frame(text) when is_binary(text), do: %Text{text: text}

  # A block equal to the last one accepted is a copy of it while a copy may still come: a NAK of
  # ours answered by more than one transmission (a damaged block that drew two errors, a NAK
  # said again to an ENQ while the first was on its way), or an ACK the sender did not see
  # (lost, or misread as the other parity) before it sent the block again. Blocks are not
  # numbered, so a new block that merely repeats the last one's text looks the same: it is
  # answered with the last ACK too, the sender finds the parity wrong, asks with ENQ, is told the
  # same, and sends it again — by then no copy is expected and it is taken. Erring this way costs
  # a round trip; erring the other way would take a block twice.
  defp duplicate?(%{accepted: nil}, _block), do: false

  defp duplicate?(%{copies: copies, accepted: accepted}, block),
    do: copies > 0 and accepted == block

  defp discard_duplicate(%{rx: rx} = data) do
    Logger.info("DNC: block #{rx.count} received again; acknowledged again and dropped")
    rx = %{rx | copies: rx.copies - 1, last: rx.ack, sent: rx.ack}
    data = bump(%{data | rx: rx}, :duplicates)
    emit(data, :retry, %{kind: :duplicate_received, block: rx.count})
    data = send_control(data, rx.ack)
    {:keep_state, data, [receive_timer(data)]}
  end

  defp reply_nak(data) do
    data = send_control(data, :nak)
    rx = %{data.rx | last: :nak, sent: :nak, naks: data.rx.naks + 1}
    data = bump(%{data | rx: rx}, :naks_sent)
    emit(data, :retry, %{kind: :nak_sent, block: data.rx.count + 1})
    {:keep_state, data, [receive_timer(data)]}
  end

  # EOT right after our NAK or WACK: the sender gave up (a working sender never ends there), so
  # what arrived is not a whole transmission and is never handed on as one.
  defp end_reception(%{rx: %{sent: sent} = rx} = data) when sent in [:nak, :wack] do
    blocks = Enum.reverse(rx.blocks)
    Logger.warning("DNC: the peer gave up its transmission after #{rx.count} blocks")

    case rx.kind do
      :reply ->
        {:next_state, :idle, %{fail(data, :aborted, rx.count + 1, nil) | rx: nil}}

      :slave ->
        notify(data, {:aborted, rx.command, blocks})
        after_slave(%{data | rx: nil})
    end
  end

  defp end_reception(%{rx: rx} = data) do
    blocks = Enum.reverse(rx.blocks)
    data = bump(data, :receptions)

    emit(data, :transmission, %{direction: :in, result: :ok}, %{
      duration: System.monotonic_time() - rx.started,
      blocks: rx.count,
      bytes: rx.bytes
    })

    case rx.kind do
      :reply ->
        reply_req(%{data | rx: nil}, data.req, {:ok, blocks}, :idle)

      :slave ->
        case rx.command do
          %Command{direction: :receive} = command when data.owner != nil ->
            ref = make_ref()
            notify(data, {:request, ref, command, blocks})
            {:next_state, :answering, %{data | rx: %{rx | ref: ref}}}

          %Command{direction: :receive} = command ->
            Logger.warning("DNC: R command #{inspect(command)} but no owner to answer it")
            after_slave(%{data | rx: nil})

          %Command{} = command ->
            notify(data, {:received, command, blocks})
            after_slave(%{data | rx: nil})

          nil ->
            notify(data, {:unsolicited, blocks})

            if data.owner == nil,
              do: Logger.info("DNC: unsolicited text from the peer: #{inspect(blocks, limit: 5)}")

            after_slave(%{data | rx: nil})
        end
    end
  end

  # After the peer's transmission: bid again for a request we yielded, or rest.
  defp after_slave(%{tx: nil} = data), do: {:next_state, :idle, data}
  defp after_slave(data), do: bid(data, [])

  ## Endings

  # Ends what is in progress with an error: the caller gets it, the owner is told, all is logged.
  defp fail(data, reason, block, count) do
    error = %LinkError{reason: reason, block: block, count: count}
    Logger.warning("DNC transmission failed: " <> Exception.message(error))
    data = bump(data, :failures)
    emit_transmission(data, reason)

    data =
      case data.req do
        nil ->
          if data.tx && data.tx.kind == :answer, do: notify(data, {:answer_failed, error})
          data

        %{from: from} ->
          :gen_statem.reply(from, {:error, error})
          %{data | req: nil}
      end

    %{data | tx: nil}
  end

  defp reply_req(data, %{from: from}, result, next_state) do
    :gen_statem.reply(from, result)
    {:next_state, next_state, %{data | req: nil}}
  end

  ## The line: sending and receiving bytes, with optional pacing at the line's baud rate

  # The GE-2000 follows its ENQ and EOT with DEL (seed §3.2); `pad` makes this end do the same.
  defp send_control(data, control) do
    pad = data.pad and control in [:enq, :eot]
    send_bytes(data, Frame.encode(control, pad: pad))
  end

  defp send_bytes(%{fault: :silent} = data, _bytes), do: data
  defp send_bytes(%{conn: nil} = data, _bytes), do: data

  defp send_bytes(%{line: %{char: nil}} = data, bytes) do
    case Transport.send(data.conn, bytes) do
      :ok -> :ok
      {:error, reason} -> Logger.warning("DNC send failed: #{inspect(reason)}")
    end

    data
  end

  defp send_bytes(%{line: line} = data, bytes) do
    # paced: the bytes reach the peer when the line has had time to carry them. A reply to what
    # was just taken off the line starts when that ended on the line, not when our timer fired.
    bytes = IO.iodata_to_binary(bytes)
    now = System.monotonic_time()

    start =
      case line.logical do
        {ended, at} when now - at <= line.slack -> ended
        _ -> now
      end

    due = max(start, line.tx_free) + byte_size(bytes) * line.char
    line = %{line | tx_free: due, tx: :queue.in({due, bytes}, line.tx)}
    %{data | line: arm(line, :tx)}
  end

  defp received(_bytes, %{fault: :silent} = data) do
    :ok = Transport.activate(data.conn)
    :keep_state_and_data
  end

  defp received(bytes, %{line: %{char: nil}} = data) do
    {frames, decoder} = Frame.feed(data.decoder, bytes)
    :ok = Transport.activate(data.conn)
    {:keep_state, proved(%{data | decoder: decoder}, frames), frame_events(frames)}
  end

  defp received(bytes, %{line: line} = data) do
    now = System.monotonic_time()

    # Our last bytes reached the peer `late` after they were due on the modelled line (a timer
    # of ours, a busy scheduler): its answer is taken to have started that much earlier, never
    # before our bytes were due. The peer's own reaction time still counts.
    start =
      case line.sent do
        {due, late} -> max(now - late, due)
        nil -> now
      end

    due = max(start, line.rx_free) + byte_size(bytes) * line.char
    line = %{line | rx_free: due, rx: :queue.in({due, bytes}, line.rx)}
    {:keep_state, %{data | line: arm(line, :rx)}}
  end

  defp flush_rx(%{line: line} = data) do
    now = System.monotonic_time()
    {ready, rest, ended} = take_due(line.rx, now + line.slack, [], now)
    line = %{line | rx: rest, timers: Map.delete(line.timers, :rx), logical: {ended, now}}
    line = arm(line, :rx)
    {frames, decoder} = Frame.feed(data.decoder, IO.iodata_to_binary(ready))
    if :queue.is_empty(rest) and data.conn, do: :ok = Transport.activate(data.conn)
    {:keep_state, proved(%{data | decoder: decoder, line: line}, frames), frame_events(frames)}
  end

  # A frame from the peer: the connection works, so a later loss is dialled again soon.
  defp proved(data, frames) do
    if Enum.any?(frames, &(not match?({:error, _}, &1))),
      do: %{data | backoff: Vws.Backoff.reset(data.backoff)},
      else: data
  end

  defp flush_tx(%{line: line} = data) do
    now = System.monotonic_time()
    {ready, rest, last} = take_due(line.tx, now + line.slack, [], nil)
    if data.conn && ready != [], do: Transport.send(data.conn, ready)
    sent = if last, do: {last, max(now - last, 0)}, else: line.sent
    line = %{line | tx: rest, timers: Map.delete(line.timers, :tx), sent: sent}
    %{data | line: arm(line, :tx)}
  end

  # Timers have millisecond resolution: what is due within `slack` (1 ms) goes now, so the error
  # averages out instead of always running late.
  defp take_due(queue, limit, acc, last) do
    case :queue.peek(queue) do
      {:value, {due, bytes}} when due <= limit ->
        take_due(:queue.drop(queue), limit, [acc | bytes], due)

      _ ->
        {acc, queue, last}
    end
  end

  # one timer per direction, for the head of its queue
  defp arm(line, dir) do
    case {line.timers[dir], :queue.peek(Map.fetch!(line, dir))} do
      {nil, {:value, {due, _}}} ->
        ms = System.convert_time_unit(due, :native, :millisecond)
        ref = :erlang.start_timer(ms, self(), :"line_#{dir}", abs: true)
        %{line | timers: Map.put(line.timers, dir, ref)}

      _ ->
        line
    end
  end

  defp frame_events(frames) do
    for f <- frames do
      case f do
        {:error, error} -> {:next_event, :internal, {:line_error, error}}
        frame -> {:next_event, :internal, {:frame, frame}}
      end
    end
  end

  ## Helpers

  defp notify(%{owner: nil}, _msg), do: :ok
  defp notify(%{owner: owner}, msg), do: send(owner, {:dnc, self(), msg})

  defp bump(data, counter), do: %{data | counters: Map.update!(data.counters, counter, &(&1 + 1))}

  defp emit(data, event, metadata, measurements \\ %{count: 1}) do
    Vws.Telemetry.execute(
      [:vws, :dnc, event],
      measurements,
      Map.merge(metadata, %{
        link: data.name,
        role: data.role,
        workstation: Vws.Names.id_of(data.name)
      })
    )
  end

  defp emit_transmission(%{tx: nil}, _result), do: :ok

  defp emit_transmission(%{tx: tx} = data, result) do
    emit(data, :transmission, %{direction: :out, kind: tx.kind, result: result}, %{
      duration: System.monotonic_time() - tx.started,
      blocks: tuple_size(tx.frames),
      bytes: tx.bytes
    })
  end
end
