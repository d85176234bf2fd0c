defmodule Vws.DDCMP.Link do
  @moduledoc false
  # The DDCMP V4.1 link as a state machine (see the state table in `Vws.DDCMP`).
  #
  # Protocol variables, all mod 256, named as in the specification:
  #   R  highest data message received in sequence
  #   N  highest data message sent (N = A + length(outstanding))
  #   A  highest data message acknowledged by the peer
  #   T  next data message to (re)transmit: A + 1 + t_index
  # `outstanding` holds the bodies of messages A+1..N in order; `t_index` counts how many of them
  # have gone out in the current pass, so a NAK (T := A+1) is `t_index = 0`. Keeping T as an
  # index avoids the mod-256 ambiguity of T = N + 1 = A when 255 messages are outstanding.
  #
  # The spec's transmit flags SACK, SNAK (with its reason) and SREP are set by the receive side and
  # served by `transmit/2` in the spec's priority (NAK, REP, retransmissions, new data, ACK) after
  # each request or each received chunk of bytes ("transmitter idle"). Every data message carries
  # RESP = R and so also serves as the ACK.

  @behaviour :gen_statem

  import Bitwise

  require Logger

  alias Vws.DDCMP.{Error, Frame}
  alias Vws.DDCMP.Frame.{Control, Data, Maintenance}
  alias Vws.Transport

  @counters [
    :sent,
    :received,
    :retransmitted,
    :naks_sent,
    :naks_received,
    :reps_sent,
    :timeouts,
    :header_crc_errors,
    :data_crc_errors,
    :restarts,
    :ignored,
    :unexpected
  ]

  @nak_for_error %{header_crc: 1, data_crc: 2, too_long: 16, header_format: 17}

  defstruct [
    # configuration
    :owner,
    :name,
    :workstation,
    :endpoint,
    :role,
    :window,
    :rep_timeout,
    :start_timeout,
    :max_failures,
    :max_data,
    :backoff,
    # transport
    :conn,
    :decoder,
    halt_reason: :disconnected,
    # start-up: does entering ISTRT send STRT (:active) or wait for the peer's (:passive)
    startup: :active,
    # protocol variables
    r: 0,
    a: 0,
    outstanding: [],
    t_index: 0,
    queue: :queue.new(),
    queue_len: 0,
    sack: false,
    snak: nil,
    srep: false,
    failures: 0,
    started_once: false,
    # sessions: counts the entries into RUNNING (each one tells the owner :up)
    session: 0,
    counters: Map.new(@counters, &{&1, 0}),
    last_error: nil
  ]

  # API called by Vws.DDCMP ---------------------------------------------------------------------

  @doc false
  def counter_names, do: @counters

  # gen_statem -----------------------------------------------------------------------------------

  @impl :gen_statem
  def callback_mode, do: [:state_functions, :state_enter]

  @impl :gen_statem
  def init(opts) do
    {min_backoff, max_backoff} = Keyword.fetch!(opts, :backoff)
    if ws = Keyword.get(opts, :workstation), do: Logger.metadata(workstation: ws)

    data = %__MODULE__{
      owner: Keyword.fetch!(opts, :owner),
      name: Keyword.get(opts, :name),
      workstation: Keyword.get(opts, :workstation),
      endpoint: Keyword.get(opts, :endpoint),
      role: Keyword.fetch!(opts, :role),
      startup: Keyword.fetch!(opts, :role),
      window: Keyword.fetch!(opts, :window),
      rep_timeout: Keyword.fetch!(opts, :rep_timeout),
      start_timeout: Keyword.fetch!(opts, :start_timeout),
      max_failures: Keyword.fetch!(opts, :max_failures),
      max_data: Keyword.fetch!(opts, :max_data),
      # doubles with every wait, back to the minimum when the link runs (Vws.Backoff)
      backoff: Vws.Backoff.new(min_backoff, max_backoff),
      decoder: Frame.new(max_data: Keyword.fetch!(opts, :max_data)),
      halt_reason: if(Keyword.has_key?(opts, :endpoint), do: :disconnected, else: :attaching)
    }

    {:ok, :halted, data}
  end

  @impl :gen_statem
  def terminate(_reason, _state, %__MODULE__{conn: conn}) do
    if conn, do: Transport.close(conn)
    :ok
  end

  # HALTED ---------------------------------------------------------------------------------------
  # No transport yet (dialling with backoff, or waiting for `attach`), or halted by a maintenance
  # message until the user restarts the link.

  @doc false
  def halted(:enter, old_state, data) do
    changed(old_state, :halted, data)

    if data.conn == nil and data.endpoint != nil do
      {delay, data} = connect_delay(data)
      {:keep_state, data, [cancel_rep_timer(), {:state_timeout, delay, :connect}]}
    else
      {:keep_state, data, [cancel_rep_timer()]}
    end
  end

  def halted(:state_timeout, :connect, data) do
    case Transport.connect(data.endpoint) do
      {:ok, conn} ->
        :ok = Transport.activate(conn)
        data = %__MODULE__{data | conn: conn, decoder: Frame.new(max_data: data.max_data)}
        {:next_state, :istrt, %__MODULE__{data | startup: data.role}}

      {:error, reason} ->
        {delay, backoff} = Vws.Backoff.next(data.backoff)

        telemetry(data, :connect_failed, %{count: 1, retry_in: delay}, %{
          endpoint: to_string(data.endpoint),
          reason: reason
        })

        {:keep_state, %__MODULE__{data | last_error: {:connect, reason}, backoff: backoff},
         [{:state_timeout, delay, :connect}]}
    end
  end

  def halted({:call, from}, {:attach, conn}, %__MODULE__{halt_reason: :attaching} = data) do
    :ok = Transport.activate(conn)
    data = %__MODULE__{data | conn: conn, startup: data.role}
    {:next_state, :istrt, data, [{:reply, from, :ok}]}
  end

  def halted({:call, from}, :restart, %__MODULE__{conn: nil} = data) do
    # Not connected: start-up begins by itself once the transport is there.
    {:keep_state, data, [{:reply, from, :ok}]}
  end

  def halted({:call, from}, :restart, data) do
    restart_link(:halted, data, :restart, [{:reply, from, :ok}])
  end

  def halted(:internal, {:send, _bytes}, _data), do: {:keep_state_and_data, [:postpone]}

  def halted(:internal, {:frame, _frame}, data), do: {:keep_state, count(data, :ignored)}
  def halted(:internal, {:bad, error}, data), do: {:keep_state, count_error(data, error)}
  def halted(:internal, :transmit, _data), do: :keep_state_and_data

  def halted(type, content, data), do: common(:halted, type, content, data)

  # ISTRT ----------------------------------------------------------------------------------------
  # We asked for a start (STRT sent, resent every start_timeout) or, passive, wait for the peer's.

  @doc false
  def istrt(:enter, old_state, data) do
    changed(old_state, :istrt, data)
    data = reset_variables(data)

    case data.startup do
      :active ->
        data = send_frames(data, [Frame.strt()])
        {:keep_state, data, [cancel_rep_timer(), {:state_timeout, data.start_timeout, :resend}]}

      :passive ->
        {:keep_state, data, [cancel_rep_timer()]}
    end
  end

  def istrt(:state_timeout, :resend, data) do
    data = data |> reset_variables() |> send_frames([Frame.strt()])
    {:keep_state, data, [{:state_timeout, data.start_timeout, :resend}]}
  end

  def istrt(:internal, {:frame, %Control{type: :strt}}, data) do
    {:next_state, :astrt, data}
  end

  def istrt(:internal, {:frame, %Control{type: :stack}}, data) do
    data = send_frames(data, [Frame.ack(0)])
    {:next_state, :running, data}
  end

  def istrt(:internal, {:frame, %Maintenance{}}, data), do: maintenance(:istrt, data)

  def istrt(:internal, {:frame, _other}, data), do: {:keep_state, count(data, :ignored)}
  def istrt(:internal, {:bad, error}, data), do: {:keep_state, count_error(data, error)}
  def istrt(:internal, :transmit, _data), do: :keep_state_and_data
  def istrt(:internal, {:send, _bytes}, _data), do: {:keep_state_and_data, [:postpone]}

  def istrt({:call, from}, :restart, data) do
    restart_link(:istrt, data, :restart, [{:reply, from, :ok}])
  end

  def istrt(type, content, data), do: common(:istrt, type, content, data)

  # ASTRT ----------------------------------------------------------------------------------------
  # We answered a STRT with STACK (resent every start_timeout) and wait for the peer to confirm.

  @doc false
  def astrt(:enter, old_state, data) do
    changed(old_state, :astrt, data)
    data = send_frames(data, [Frame.stack()])
    {:keep_state, data, [cancel_rep_timer(), {:state_timeout, data.start_timeout, :resend}]}
  end

  def astrt(:state_timeout, :resend, data) do
    data = send_frames(data, [Frame.stack()])
    {:keep_state, data, [{:state_timeout, data.start_timeout, :resend}]}
  end

  def astrt(:internal, {:frame, %Control{type: :strt}}, data) do
    data = send_frames(data, [Frame.stack()])
    {:keep_state, data, [{:state_timeout, data.start_timeout, :resend}]}
  end

  def astrt(:internal, {:frame, %Control{type: :stack}}, data) do
    data = send_frames(data, [Frame.ack(0)])
    {:next_state, :running, data}
  end

  def astrt(:internal, {:frame, %Control{type: :ack, rcvr: 0}}, data) do
    {:next_state, :running, data}
  end

  def astrt(:internal, {:frame, %Data{resp: 0} = frame}, data) do
    # The peer is running: the message is processed as in RUNNING.
    {:next_state, :running, data, [{:next_event, :internal, {:frame, frame}}]}
  end

  def astrt(:internal, {:frame, %Maintenance{}}, data), do: maintenance(:astrt, data)

  def astrt(:internal, {:frame, _other}, data), do: {:keep_state, count(data, :ignored)}
  def astrt(:internal, {:bad, error}, data), do: {:keep_state, count_error(data, error)}
  def astrt(:internal, :transmit, _data), do: :keep_state_and_data
  def astrt(:internal, {:send, _bytes}, _data), do: {:keep_state_and_data, [:postpone]}

  def astrt({:call, from}, :restart, data) do
    restart_link(:astrt, data, :restart, [{:reply, from, :ok}])
  end

  def astrt(type, content, data), do: common(:astrt, type, content, data)

  # RUNNING --------------------------------------------------------------------------------------

  @doc false
  def running(:enter, old_state, data) do
    changed(old_state, :running, data)
    notify(data, :up)

    {:keep_state,
     %__MODULE__{
       data
       | failures: 0,
         backoff: Vws.Backoff.reset(data.backoff),
         session: data.session + 1
     }}
  end

  def running(:internal, {:send, bytes}, data) do
    data = %__MODULE__{data | queue: :queue.in(bytes, data.queue), queue_len: data.queue_len + 1}
    transmit(data)
  end

  def running(:internal, :transmit, data), do: transmit(data)

  def running(:internal, {:frame, %Data{} = frame}, data) do
    data = data |> acknowledged(frame.resp) |> receive_data(frame)
    {:keep_state, data}
  end

  def running(:internal, {:frame, %Control{type: :ack, rcvr: resp}}, data) do
    {:keep_state, acknowledged(data, resp)}
  end

  def running(:internal, {:frame, %Control{type: :nak} = nak}, data) do
    telemetry(data, :nak, %{count: 1}, %{
      direction: :received,
      reason: Frame.nak_reason(nak.subtype),
      resp: nak.rcvr
    })

    if in_range?(nak.rcvr, data.a, n(data), _including_a = true) do
      # Everything up to RESP arrived; the rest is sent again from A+1.
      data = data |> acknowledged(nak.rcvr) |> count(:naks_received)

      # A NAK answering our REP (reason 3) is the REP timeout's outcome, already counted.
      failure = if nak.subtype == Frame.nak_code(:rep_response), do: 0, else: 1

      data = %__MODULE__{
        data
        | t_index: 0,
          failures: data.failures + failure,
          last_error: {:nak, Frame.nak_reason(nak.subtype)}
      }

      if data.failures >= data.max_failures do
        too_many_failures(data)
      else
        {:keep_state, data, [cancel_rep_timer()]}
      end
    else
      {:keep_state, count(data, :ignored)}
    end
  end

  def running(:internal, {:frame, %Control{type: :rep, sndr: num}}, data) do
    telemetry(data, :rep, %{count: 1}, %{direction: :received, num: num})

    if num == data.r do
      {:keep_state, set_sack(data)}
    else
      {:keep_state, set_snak(data, Frame.nak_code(:rep_response))}
    end
  end

  def running(:internal, {:frame, %Control{type: :stack}}, data) do
    {:keep_state, set_sack(data)}
  end

  def running(:internal, {:frame, %Control{type: :strt} = strt}, data) do
    # The peer restarted: whatever was outstanding is lost. The spec halts and notifies the user;
    # our user policy is to start up again at once. A passive link answers the STRT it got.
    notify(data, :peer_restarted)
    data = %__MODULE__{data | last_error: :peer_restarted}
    data = drop_queue(data) |> count(:restarts)
    data = %__MODULE__{data | startup: data.role}

    case data.role do
      :active -> {:next_state, :istrt, data}
      :passive -> {:next_state, :istrt, data, [{:next_event, :internal, {:frame, strt}}]}
    end
  end

  def running(:internal, {:frame, %Maintenance{}}, data), do: maintenance(:running, data)

  def running(:internal, {:bad, %Error{reason: reason} = error}, data) do
    data = count_error(data, error)

    data =
      if reason in [:data_crc, :too_long] and is_integer(error.resp),
        do: acknowledged(data, error.resp),
        else: data

    {:keep_state, set_snak(data, Map.fetch!(@nak_for_error, reason))}
  end

  def running({:timeout, :rep}, :rep, data) do
    if data.outstanding == [] do
      :keep_state_and_data
    else
      data = %__MODULE__{count(data, :timeouts) | failures: data.failures + 1}
      data = %__MODULE__{data | last_error: :rep_timeout}

      if data.failures >= data.max_failures do
        too_many_failures(data)
      else
        transmit(%__MODULE__{data | srep: true})
      end
    end
  end

  def running({:call, from}, :restart, data) do
    restart_link(:running, data, :restart, [{:reply, from, :ok}])
  end

  def running(type, content, data), do: common(:running, type, content, data)

  # Events every state handles the same way ------------------------------------------------------

  # The request is answered at once; the message itself waits (postponed) until RUNNING.
  defp common(_state, {:call, from}, {:send, bytes}, data) when is_binary(bytes) do
    if byte_size(bytes) > data.max_data do
      {:keep_state_and_data, [{:reply, from, {:error, :too_long}}]}
    else
      {:keep_state_and_data, [{:reply, from, :ok}, {:next_event, :internal, {:send, bytes}}]}
    end
  end

  defp common(state, {:call, from}, {:send_now, bytes}, data) when is_binary(bytes) do
    if state == :running do
      common(state, {:call, from}, {:send, bytes}, data)
    else
      {:keep_state_and_data, [{:reply, from, {:error, :not_running}}]}
    end
  end

  # Only into the session the owner means: an answer to a message of an ended session is refused
  # even when the link is RUNNING again (in a later session).
  defp common(state, {:call, from}, {:send_in, session, bytes}, data) when is_binary(bytes) do
    if state == :running and session == data.session do
      common(state, {:call, from}, {:send, bytes}, data)
    else
      {:keep_state_and_data, [{:reply, from, {:error, :not_running}}]}
    end
  end

  defp common(state, {:call, from}, :info, data) do
    {:keep_state_and_data, [{:reply, from, info(state, data)}]}
  end

  defp common(state, :info, message, %__MODULE__{conn: conn} = data) when conn != nil do
    case Transport.handle_message(conn, message) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        {items, decoder} = Frame.feed(data.decoder, bytes)

        for %{} = frame <- items do
          telemetry(data, :frame_received, %{count: 1}, frame_meta(frame))
        end

        events = Enum.map(items, &item_event/1) ++ [{:next_event, :internal, :transmit}]
        {:keep_state, %__MODULE__{data | decoder: decoder}, events}

      :closed ->
        disconnected(state, data, :closed)

      {:error, reason} ->
        disconnected(state, data, {:transport, reason})

      :unknown ->
        unexpected(state, :info, message, data)
    end
  end

  defp common(state, {:call, from} = type, content, data) do
    {:keep_state, data, actions} = unexpected(state, type, content, data)
    {:keep_state, data, [{:reply, from, {:error, :unknown_call}} | actions]}
  end

  defp common(state, type, content, data), do: unexpected(state, type, content, data)

  defp unexpected(state, type, content, data) do
    Logger.warning(
      "DDCMP link #{inspect(data.name || self())} in #{state}: unexpected #{inspect(type)} " <>
        inspect(content, limit: 10)
    )

    {:keep_state, count(data, :unexpected), []}
  end

  defp item_event({:error, %Error{} = error}), do: {:next_event, :internal, {:bad, error}}
  defp item_event(frame), do: {:next_event, :internal, {:frame, frame}}

  # Transitions ----------------------------------------------------------------------------------

  defp changed(old_state, new_state, data) do
    if old_state != new_state do
      Logger.debug("DDCMP link #{inspect(data.name || self())}: #{old_state} -> #{new_state}")
      telemetry(data, :state_change, %{count: 1}, %{from: old_state, to: new_state})
    end
  end

  # restart/1 (and a halted link's restart): STRT and back through start-up.
  defp restart_link(state, data, reason, actions) do
    if state == :running, do: link_down(data, reason)
    data = data |> drop_queue() |> count(:restarts)
    data = %__MODULE__{data | startup: :active}

    case state do
      :istrt -> {:repeat_state, data, actions}
      _ -> {:next_state, :istrt, data, actions}
    end
  end

  defp too_many_failures(data) do
    link_down(data, :too_many_failures)
    data = data |> drop_queue() |> count(:restarts)
    {:next_state, :istrt, %__MODULE__{data | startup: data.role, last_error: :too_many_failures}}
  end

  defp maintenance(state, data) do
    if state == :running, do: link_down(data, :maintenance)
    data = drop_queue(data)

    {:next_state, :halted,
     %__MODULE__{data | halt_reason: :maintenance, last_error: :maintenance}}
  end

  defp disconnected(state, data, reason) do
    Transport.close(data.conn)
    data = drop_queue(%__MODULE__{data | conn: nil, last_error: reason})

    cond do
      data.endpoint != nil ->
        if state == :running, do: link_down(data, reason)
        {:next_state, :halted, %__MODULE__{data | halt_reason: :disconnected}}

      true ->
        # A handed-over connection cannot be dialled again: the link's life ends with it.
        link_down(data, reason)
        {:stop, :normal, data}
    end
  end

  defp link_down(data, reason) do
    telemetry(data, :link_down, %{count: 1}, %{reason: reason})
    notify(data, {:down, reason})
  end

  # The first dial goes at once; later ones after the back-off's next wait. A connection that
  # never reached RUNNING proved nothing: the wait goes on doubling (Vws.Backoff).
  defp connect_delay(%__MODULE__{started_once: false} = data), do: {0, data}

  defp connect_delay(data) do
    {delay, backoff} = Vws.Backoff.next(data.backoff)
    {delay, %__MODULE__{data | backoff: backoff}}
  end

  defp reset_variables(data) do
    %__MODULE__{
      data
      | r: 0,
        a: 0,
        outstanding: [],
        t_index: 0,
        sack: false,
        snak: nil,
        srep: false,
        failures: 0,
        started_once: true
    }
  end

  defp drop_queue(data) do
    %__MODULE__{data | outstanding: [], t_index: 0, queue: :queue.new(), queue_len: 0}
  end

  # Receiving in RUNNING -------------------------------------------------------------------------

  # Any RESP with A < RESP <= N acknowledges A+1..RESP; anything else is ignored.
  defp acknowledged(data, resp) do
    if in_range?(resp, data.a, n(data), _including_a = false) do
      acked = dist(data.a, resp)
      outstanding = Enum.drop(data.outstanding, acked)

      %__MODULE__{
        data
        | a: resp,
          outstanding: outstanding,
          t_index: max(data.t_index - acked, 0),
          failures: 0
      }
    else
      data
    end
  end

  defp receive_data(data, %Data{num: num, data: bytes}) do
    if num == seq(data.r + 1) do
      notify(data, {:data, bytes})
      data = %__MODULE__{data | r: num} |> count(:received)
      set_sack(data)
    else
      # Out of sequence (a duplicate, or one after a lost message): discarded. The sender
      # recovers through its REP timer or our NAK for the message that was lost.
      count(data, :ignored)
    end
  end

  defp set_sack(data), do: %__MODULE__{data | sack: true, snak: nil}
  defp set_snak(data, reason), do: %__MODULE__{data | snak: reason, sack: false}

  # Transmitting in RUNNING ----------------------------------------------------------------------

  defp transmit(data) do
    {frames, data} = {[], data} |> nak() |> rep() |> retransmit() |> new_data() |> ack()
    data = send_frames(data, Enum.reverse(frames))

    sent_timed? =
      Enum.any?(frames, fn
        %Data{} -> true
        %Control{type: :rep} -> true
        _ -> false
      end)

    timer =
      cond do
        data.outstanding == [] -> [cancel_rep_timer()]
        sent_timed? -> [{{:timeout, :rep}, data.rep_timeout, :rep}]
        true -> []
      end

    {:keep_state, data, timer}
  end

  defp nak({frames, %__MODULE__{snak: nil} = data}), do: {frames, data}

  defp nak({frames, %__MODULE__{snak: reason} = data}) do
    telemetry(data, :nak, %{count: 1}, %{
      direction: :sent,
      reason: Frame.nak_reason(reason),
      resp: data.r
    })

    {[Frame.nak(reason, data.r) | frames], %__MODULE__{count(data, :naks_sent) | snak: nil}}
  end

  defp rep({frames, %__MODULE__{srep: false} = data}), do: {frames, data}

  defp rep({frames, data}) do
    telemetry(data, :rep, %{count: 1}, %{direction: :sent, num: n(data)})
    {[Frame.rep(n(data)) | frames], %__MODULE__{count(data, :reps_sent) | srep: false}}
  end

  defp retransmit({frames, data}) do
    pending = Enum.drop(data.outstanding, data.t_index)

    {frames, _} =
      Enum.reduce(pending, {frames, seq(data.a + 1 + data.t_index)}, fn bytes, {frames, num} ->
        telemetry(data, :retransmission, %{count: 1, bytes: byte_size(bytes)}, %{num: num})
        {[Frame.data(num, data.r, bytes) | frames], seq(num + 1)}
      end)

    retransmitted = length(pending)

    data = %__MODULE__{
      data
      | t_index: length(data.outstanding),
        counters: Map.update!(data.counters, :retransmitted, &(&1 + retransmitted))
    }

    data = if retransmitted > 0, do: %__MODULE__{data | sack: false}, else: data
    {frames, data}
  end

  defp new_data({frames, data}) do
    if data.queue_len > 0 and length(data.outstanding) < data.window do
      {{:value, bytes}, queue} = :queue.out(data.queue)
      num = seq(n(data) + 1)

      data =
        %__MODULE__{
          data
          | queue: queue,
            queue_len: data.queue_len - 1,
            outstanding: data.outstanding ++ [bytes],
            t_index: data.t_index + 1,
            sack: false
        }
        |> count(:sent)

      new_data({[Frame.data(num, data.r, bytes) | frames], data})
    else
      {frames, data}
    end
  end

  defp ack({frames, %__MODULE__{sack: true} = data}) do
    {[Frame.ack(data.r) | frames], %__MODULE__{data | sack: false}}
  end

  defp ack(acc), do: acc

  defp send_frames(data, []), do: data

  defp send_frames(%__MODULE__{conn: conn} = data, frames) do
    iodata = Enum.map(frames, &Frame.encode/1)

    for frame <- frames do
      telemetry(data, :frame_sent, %{count: 1}, frame_meta(frame))
    end

    case Transport.send(conn, iodata) do
      :ok ->
        data

      {:error, reason} ->
        # The transport reports the close itself; until then the link keeps its state.
        %__MODULE__{data | last_error: {:send, reason}}
    end
  end

  defp frame_meta(%Data{num: num, resp: resp, data: bytes}),
    do: %{type: :data, num: num, resp: resp, bytes: byte_size(bytes)}

  defp frame_meta(%Control{type: type, subtype: subtype, rcvr: rcvr, sndr: sndr}),
    do: %{type: type, subtype: subtype, rcvr: rcvr, sndr: sndr}

  defp frame_meta(%Maintenance{data: bytes}), do: %{type: :maintenance, bytes: byte_size(bytes)}

  defp cancel_rep_timer, do: {{:timeout, :rep}, :cancel}

  # Bookkeeping ----------------------------------------------------------------------------------

  defp n(data), do: seq(data.a + length(data.outstanding))

  defp seq(x), do: band(x, 0xFF)

  defp dist(from, to), do: band(to - from, 0xFF)

  # A < x <= N (or A <= x <= N), mod 256.
  defp in_range?(x, a, n, including_a) do
    d = dist(a, x)
    (d > 0 or including_a) and d <= dist(a, n)
  end

  defp count(data, counter) do
    %__MODULE__{data | counters: Map.update!(data.counters, counter, &(&1 + 1))}
  end

  defp count_error(data, %Error{reason: reason} = error) do
    data = %__MODULE__{data | last_error: {:receive, reason}}
    telemetry(data, :receive_error, %{count: 1}, %{reason: reason, num: error.num})

    case reason do
      :header_crc -> count(data, :header_crc_errors)
      :data_crc -> count(data, :data_crc_errors)
      _ -> count(data, :ignored)
    end
  end

  defp notify(data, event) do
    case resolve(data.owner) do
      nil -> :ok
      pid -> send(pid, {:ddcmp, self(), event})
    end
  end

  defp resolve(pid) when is_pid(pid), do: pid
  defp resolve(name), do: GenServer.whereis(name)

  defp telemetry(data, event, measurements, metadata) do
    Vws.Telemetry.execute(
      [:vws, :ddcmp, event],
      measurements,
      Map.merge(metadata, %{link: data.name || self(), workstation: data.workstation})
    )
  end

  defp info(state, data) do
    %{
      state: state,
      role: data.role,
      connected: data.conn != nil,
      peer: data.conn && Transport.peer(data.conn),
      session: data.session,
      r: data.r,
      n: n(data),
      a: data.a,
      t: seq(data.a + 1 + data.t_index),
      window: data.window,
      outstanding: length(data.outstanding),
      queue: data.queue_len,
      failures: data.failures,
      counters: data.counters,
      halt_reason: if(state == :halted, do: data.halt_reason),
      last_error: data.last_error
    }
  end
end
