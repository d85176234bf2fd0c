defmodule Vws.Links.DDCMP.Protocol do
  @moduledoc """
  DDCMP V4.1 as data: the link's state machine (the table in `Vws.Links.DDCMP`) as a struct and pure
  functions, in the style of Mint's `Mint.HTTP1`. No process, no I/O, no timers, no logging.

  Every function that moves the protocol returns `{protocol, frames, events}`:

    * `frames` — `Vws.Links.DDCMP.Frame` structs to write to the line, in order (each followed by one
      DEL when encoded with `Vws.Links.DDCMP.Frame.encode/1`);
    * `events`, in order, for the process around it:
      * `:up` — start-up completed, RUNNING (a new session begins, see `session/1`);
      * `{:data, binary}` — a data message from the peer, in order, each once;
      * `{:down, reason}` — RUNNING ended: `:too_many_failures`, `:restart`, `:maintenance`, or the
        reason given to `disconnected/2`;
      * `:peer_restarted` — a STRT arrived while RUNNING;
      * `{:timer, :rep | :start, milliseconds | :cancel}` — (re)arm or cancel a timer; when it
        expires call `handle_timeout/2` with its name;
      * `{:telemetry, event, measurements, metadata}` — a `[:vws, :ddcmp, event]` point (see
        `Vws.Links.DDCMP`, "Telemetry"; the caller adds `link` and `workstation`).

  Two protocols wired back to back exchange messages with no process at all:

      iex> alias Vws.Links.DDCMP.{Frame, Protocol}
      iex> wire = fn frames -> frames |> Enum.map(&Frame.encode/1) |> IO.iodata_to_binary() end
      iex> {cec, strt, _} = Protocol.connect(Protocol.new(role: :active))
      iex> {val, stack, _} = Protocol.connect(Protocol.new(role: :passive)) |> elem(0) |> Protocol.handle_bytes(wire.(strt))
      iex> {cec, ack, events} = Protocol.handle_bytes(cec, wire.(stack))
      iex> :up in events
      true
      iex> {val, [], events} = Protocol.handle_bytes(val, wire.(ack))
      iex> :up in events
      true
      iex> {:ok, _cec, data, _} = Protocol.send(cec, "WHERE")
      iex> {_val, [%Frame.Control{type: :ack, rcvr: 1}], events} = Protocol.handle_bytes(val, wire.(data))
      iex> {:data, "WHERE"} in events
      true
  """

  # what this core returns as {:telemetry, name, …} its process emits as [:vws, :ddcmp, name]
  @telemetry_prefix [:vws, :ddcmp]

  @doc false
  def telemetry_prefix, do: @telemetry_prefix

  import Bitwise

  alias Vws.Links.DDCMP.{Error, Frame}
  alias Vws.Links.DDCMP.Frame.{Control, Data, Maintenance}

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
  # served by `transmit/1` in the spec's priority (NAK, REP, retransmissions, new data, ACK) after
  # each request or each received chunk of bytes ("transmitter idle"). Every data message carries
  # RESP = R and so also serves as the ACK.
  #
  # `held` are messages given before RUNNING: they wait for it and survive restarts (the user
  # asked for them to go once the link runs); `queue` are messages given while RUNNING that wait
  # for the window, dropped with `outstanding` whenever RUNNING ends.
  defstruct role: :active,
            window: 7,
            rep_timeout: 3000,
            start_timeout: 3000,
            max_failures: 8,
            max_data: 4096,
            state: :halted,
            halt_reason: :disconnected,
            connected: false,
            decoder: nil,
            startup: :active,
            r: 0,
            a: 0,
            outstanding: [],
            t_index: 0,
            queue: :queue.new(),
            queue_len: 0,
            held: :queue.new(),
            sack: false,
            snak: nil,
            srep: false,
            failures: 0,
            session: 0,
            counters: Map.new(@counters, &{&1, 0}),
            last_error: nil,
            # what one call produces, newest first; emptied when the call returns
            out: [],
            events: []

  @type state :: :halted | :istrt | :astrt | :running
  @type event ::
          :up
          | {:data, binary}
          | {:down, term}
          | :peer_restarted
          | {:timer, :rep | :start, pos_integer | :cancel}
          | {:telemetry, atom, map, map}
  @type t :: %__MODULE__{}
  @type result :: {t, [Frame.t()], [event]}

  @doc "The names of the counters in `info/1`."
  @spec counter_names() :: [atom]
  def counter_names, do: @counters

  @doc """
  A halted protocol, not yet connected. Options (validated by the caller, see `Vws.Links.DDCMP`):
  `:role`, `:window`, `:rep_timeout`, `:start_timeout`, `:max_failures`, `:max_data`, and
  `:halt_reason` (what `info/1` says until `connect/1`, default `:disconnected`).
  """
  @spec new(keyword) :: t
  def new(opts \\ []) do
    p =
      struct!(
        __MODULE__,
        Keyword.take(opts, [
          :role,
          :window,
          :rep_timeout,
          :start_timeout,
          :max_failures,
          :max_data,
          :halt_reason
        ])
      )

    %__MODULE__{p | startup: p.role, decoder: Frame.new(max_data: p.max_data)}
  end

  @doc "The state: `:halted`, `:istrt`, `:astrt` or `:running`."
  @spec state(t) :: state
  def state(%__MODULE__{state: state}), do: state

  @doc "True while RUNNING."
  @spec running?(t) :: boolean
  def running?(%__MODULE__{state: state}), do: state == :running

  @doc "The number of the latest session (the count of `:up` events so far; 0 before the first)."
  @spec session(t) :: non_neg_integer
  def session(%__MODULE__{session: session}), do: session

  @doc """
  The transport is up: start-up begins (`:active` sends STRT, `:passive` waits for the peer's).
  """
  @spec connect(t) :: result
  def connect(%__MODULE__{} = p) do
    p = %__MODULE__{p | connected: true, decoder: Frame.new(max_data: p.max_data)}
    p |> enter(:istrt, p.role) |> flush()
  end

  @doc """
  The transport is gone (`reason` e.g. `:closed` or `{:transport, reason}`): `{:down, reason}`
  if RUNNING; HALTED until `connect/1`. Messages outstanding and queued are dropped.
  """
  @spec disconnected(t, term) :: result
  def disconnected(%__MODULE__{} = p, reason) do
    p = if p.state == :running, do: link_down(p, reason), else: p
    p = drop_queue(%__MODULE__{p | connected: false, last_error: reason})
    p |> enter(:halted) |> put(:halt_reason, :disconnected) |> flush()
  end

  @doc """
  Re-initialises the link (the user's restart): STRT and back through start-up;
  `{:down, :restart}` if it was RUNNING. Unconnected, it does nothing: start-up begins with
  `connect/1`.
  """
  @spec restart(t) :: result
  def restart(%__MODULE__{connected: false} = p), do: flush(p)

  def restart(%__MODULE__{} = p) do
    p = if p.state == :running, do: link_down(p, :restart), else: p
    p = p |> drop_queue() |> count(:restarts)
    p |> enter(:istrt, :active) |> flush()
  end

  @doc """
  Queues a data message. Options: `hold: false` refuses it unless RUNNING; `session: n` refuses
  it unless RUNNING in session `n`; otherwise a message given before RUNNING waits for it.
  Returns `{:ok, protocol, frames, events}`, or `{:error, :too_long | :not_running}`.
  """
  @spec send(t, iodata, keyword) :: {:ok, t, [Frame.t()], [event]} | {:error, atom}
  def send(%__MODULE__{} = p, iodata, opts \\ []) do
    bytes = IO.iodata_to_binary(iodata)
    running = p.state == :running

    cond do
      byte_size(bytes) > p.max_data ->
        {:error, :too_long}

      Keyword.has_key?(opts, :session) and not (running and opts[:session] == p.session) ->
        {:error, :not_running}

      Keyword.get(opts, :hold, true) == false and not running ->
        {:error, :not_running}

      running ->
        p = %__MODULE__{p | queue: :queue.in(bytes, p.queue), queue_len: p.queue_len + 1}
        {p, frames, events} = p |> transmit() |> flush()
        {:ok, p, frames, events}

      true ->
        {:ok, %__MODULE__{p | held: :queue.in(bytes, p.held)}, [], []}
    end
  end

  @doc "Bytes from the line: frames are decoded and handled in order, then the transmitter runs."
  @spec handle_bytes(t, iodata) :: result
  def handle_bytes(%__MODULE__{} = p, bytes) do
    {items, decoder} = Frame.feed(p.decoder, bytes)
    p = %__MODULE__{p | decoder: decoder}

    p =
      Enum.reduce(items, p, fn
        {:error, %Error{} = error}, p ->
          bad(p.state, error, p)

        frame, p ->
          p |> telemetry(:frame_received, %{count: 1}, frame_meta(frame)) |> frame(p.state, frame)
      end)

    p = if p.state == :running, do: transmit(p), else: p
    flush(p)
  end

  @doc "A timer armed by an earlier `{:timer, name, ms}` event expired. Stale ones do nothing."
  @spec handle_timeout(t, :rep | :start) :: result
  def handle_timeout(%__MODULE__{state: :istrt, startup: :active} = p, :start) do
    p |> reset_variables() |> out(Frame.strt()) |> timer(:start, p.start_timeout) |> flush()
  end

  def handle_timeout(%__MODULE__{state: :astrt} = p, :start) do
    p |> out(Frame.stack()) |> timer(:start, p.start_timeout) |> flush()
  end

  def handle_timeout(%__MODULE__{state: :running, outstanding: [_ | _]} = p, :rep) do
    p = %__MODULE__{count(p, :timeouts) | failures: p.failures + 1, last_error: :rep_timeout}

    if p.failures >= p.max_failures,
      do: p |> too_many_failures() |> flush(),
      else: %__MODULE__{p | srep: true} |> transmit() |> flush()
  end

  def handle_timeout(%__MODULE__{} = p, _timer), do: flush(p)

  @doc "Counts something the process around the protocol did not expect (`counters.unexpected`)."
  @spec count_unexpected(t) :: t
  def count_unexpected(%__MODULE__{} = p), do: count(p, :unexpected)

  @doc """
  The state and numbers: `state`, `role`, `session`, `r`, `n`, `a`, `t`, `window`,
  `outstanding`, `queue`, `failures`, `counters`, `halt_reason` (HALTED only), `last_error`.
  """
  @spec info(t) :: map
  def info(%__MODULE__{} = p) do
    %{
      state: p.state,
      role: p.role,
      session: p.session,
      r: p.r,
      n: n(p),
      a: p.a,
      t: seq(p.a + 1 + p.t_index),
      window: p.window,
      outstanding: length(p.outstanding),
      queue: p.queue_len,
      failures: p.failures,
      counters: p.counters,
      halt_reason: if(p.state == :halted, do: p.halt_reason),
      last_error: p.last_error
    }
  end

  # Frames, state by state -----------------------------------------------------------------------

  defp frame(p, :halted, _frame), do: count(p, :ignored)
  defp frame(p, _state, %Maintenance{}), do: maintenance(p)

  defp frame(p, :istrt, %Control{type: :strt}), do: enter(p, :astrt)
  defp frame(p, :istrt, %Control{type: :stack}), do: p |> out(Frame.ack(0)) |> enter(:running)
  defp frame(p, :istrt, _frame), do: count(p, :ignored)

  defp frame(p, :astrt, %Control{type: :strt}),
    do: p |> out(Frame.stack()) |> timer(:start, p.start_timeout)

  defp frame(p, :astrt, %Control{type: :stack}), do: p |> out(Frame.ack(0)) |> enter(:running)
  defp frame(p, :astrt, %Control{type: :ack, rcvr: 0}), do: enter(p, :running)
  # the peer is running: the message is handled as in RUNNING
  defp frame(p, :astrt, %Data{resp: 0} = data), do: p |> enter(:running) |> frame(:running, data)
  defp frame(p, :astrt, _frame), do: count(p, :ignored)

  defp frame(p, :running, %Data{} = data), do: p |> acknowledged(data.resp) |> receive_data(data)
  defp frame(p, :running, %Control{type: :ack, rcvr: resp}), do: acknowledged(p, resp)

  defp frame(p, :running, %Control{type: :nak} = nak) do
    p =
      telemetry(p, :nak, %{count: 1}, %{
        direction: :received,
        reason: Frame.nak_reason(nak.subtype),
        resp: nak.rcvr
      })

    if in_range?(nak.rcvr, p.a, n(p), _including_a = true) do
      # Everything up to RESP arrived; the rest is sent again from A+1.
      p = p |> acknowledged(nak.rcvr) |> count(:naks_received)
      # A NAK answering our REP (reason 3) is the REP timeout's outcome, already counted.
      failure = if nak.subtype == Frame.nak_code(:rep_response), do: 0, else: 1

      p = %__MODULE__{
        p
        | t_index: 0,
          failures: p.failures + failure,
          last_error: {:nak, Frame.nak_reason(nak.subtype)}
      }

      if p.failures >= p.max_failures,
        do: too_many_failures(p),
        else: timer(p, :rep, :cancel)
    else
      count(p, :ignored)
    end
  end

  defp frame(p, :running, %Control{type: :rep, sndr: num}) do
    p = telemetry(p, :rep, %{count: 1}, %{direction: :received, num: num})
    if num == p.r, do: set_sack(p), else: set_snak(p, Frame.nak_code(:rep_response))
  end

  defp frame(p, :running, %Control{type: :stack}), do: set_sack(p)

  defp frame(p, :running, %Control{type: :strt} = strt) do
    # The peer restarted: whatever was outstanding is lost. The spec halts and notifies the user;
    # our user policy is to start up again at once. A passive link answers the STRT it got.
    p = emit(p, :peer_restarted)
    p = %__MODULE__{p | last_error: :peer_restarted} |> drop_queue() |> count(:restarts)

    case p.role do
      :active -> enter(p, :istrt, :active)
      :passive -> p |> enter(:istrt, :passive) |> frame(:istrt, strt)
    end
  end

  defp bad(:running, %Error{reason: reason} = error, p) do
    p = count_error(p, error)

    p =
      if reason in [:data_crc, :too_long] and is_integer(error.resp),
        do: acknowledged(p, error.resp),
        else: p

    set_snak(p, Map.fetch!(@nak_for_error, reason))
  end

  defp bad(_state, error, p), do: count_error(p, error)

  # Transitions ----------------------------------------------------------------------------------

  # Entering a state: the spec's entry actions. Every entry cancels both timers first, so a state's
  # own timer is the only one armed (what gen_statem's state_timeout gave the old link process).
  defp enter(p, new, startup \\ nil)

  defp enter(p, :istrt, startup) do
    p = changed(p, :istrt) |> reset_variables()
    p = %__MODULE__{p | startup: startup || p.startup}

    case p.startup do
      :active -> p |> out(Frame.strt()) |> timer(:start, p.start_timeout)
      :passive -> p
    end
  end

  defp enter(p, :astrt, _),
    do: p |> changed(:astrt) |> out(Frame.stack()) |> timer(:start, p.start_timeout)

  defp enter(p, :running, _) do
    p = changed(p, :running) |> emit(:up)
    held = :queue.to_list(p.held)

    %__MODULE__{
      p
      | failures: 0,
        session: p.session + 1,
        queue: :queue.join(p.queue, p.held),
        queue_len: p.queue_len + length(held),
        held: :queue.new()
    }
  end

  defp enter(p, :halted, _), do: changed(p, :halted)

  defp changed(%__MODULE__{state: old} = p, new) do
    p = p |> timer(:rep, :cancel) |> timer(:start, :cancel)

    p =
      if old != new,
        do: telemetry(p, :state_change, %{count: 1}, %{from: old, to: new}),
        else: p

    %__MODULE__{p | state: new}
  end

  # Whatever the role, the start-up after declaring the link down is this side's to begin (STRT):
  # the peer may have nothing outstanding, no timer running, and would never learn that this
  # side stopped — a passive side waiting in ISTRT for a STRT that does not come, and a peer
  # waiting in RUNNING for an answer lost with the old stream. `:passive` is how a link starts
  # when its transport comes up, not how it restarts.
  defp too_many_failures(p) do
    p = p |> link_down(:too_many_failures) |> drop_queue() |> count(:restarts)
    p = %__MODULE__{p | last_error: :too_many_failures}
    enter(p, :istrt, :active)
  end

  defp maintenance(p) do
    p = if p.state == :running, do: link_down(p, :maintenance), else: p
    p = drop_queue(%__MODULE__{p | last_error: :maintenance})
    p |> enter(:halted) |> put(:halt_reason, :maintenance)
  end

  defp link_down(p, reason) do
    p |> telemetry(:link_down, %{count: 1}, %{reason: reason}) |> emit({:down, reason})
  end

  defp reset_variables(p) do
    %__MODULE__{
      p
      | r: 0,
        a: 0,
        outstanding: [],
        t_index: 0,
        sack: false,
        snak: nil,
        srep: false,
        failures: 0
    }
  end

  defp drop_queue(p),
    do: %__MODULE__{p | outstanding: [], t_index: 0, queue: :queue.new(), queue_len: 0}

  # Receiving in RUNNING -------------------------------------------------------------------------

  # Any RESP with A < RESP <= N acknowledges A+1..RESP; anything else is ignored.
  defp acknowledged(p, resp) do
    if in_range?(resp, p.a, n(p), _including_a = false) do
      acked = dist(p.a, resp)

      %__MODULE__{
        p
        | a: resp,
          outstanding: Enum.drop(p.outstanding, acked),
          t_index: max(p.t_index - acked, 0),
          failures: 0
      }
    else
      p
    end
  end

  defp receive_data(p, %Data{num: num, data: bytes}) do
    if num == seq(p.r + 1) do
      %__MODULE__{p | r: num} |> emit({:data, bytes}) |> count(:received) |> set_sack()
    else
      # Out of sequence (a duplicate, or one after a lost message): discarded. The sender
      # recovers through its REP timer or our NAK for the message that was lost.
      count(p, :ignored)
    end
  end

  defp set_sack(p), do: %__MODULE__{p | sack: true, snak: nil}
  defp set_snak(p, reason), do: %__MODULE__{p | snak: reason, sack: false}

  # Transmitting in RUNNING ----------------------------------------------------------------------

  defp transmit(p) do
    before = length(p.out)
    p = p |> nak() |> rep() |> retransmit() |> new_data() |> ack()

    sent_timed? =
      p.out
      |> Enum.take(length(p.out) - before)
      |> Enum.any?(&(match?(%Data{}, &1) or match?(%Control{type: :rep}, &1)))

    cond do
      p.outstanding == [] -> timer(p, :rep, :cancel)
      sent_timed? -> timer(p, :rep, p.rep_timeout)
      true -> p
    end
  end

  defp nak(%__MODULE__{snak: nil} = p), do: p

  defp nak(%__MODULE__{snak: reason} = p) do
    p
    |> telemetry(:nak, %{count: 1}, %{
      direction: :sent,
      reason: Frame.nak_reason(reason),
      resp: p.r
    })
    |> out(Frame.nak(reason, p.r))
    |> count(:naks_sent)
    |> put(:snak, nil)
  end

  defp rep(%__MODULE__{srep: false} = p), do: p

  defp rep(p) do
    p
    |> telemetry(:rep, %{count: 1}, %{direction: :sent, num: n(p)})
    |> out(Frame.rep(n(p)))
    |> count(:reps_sent)
    |> put(:srep, false)
  end

  defp retransmit(p) do
    pending = Enum.drop(p.outstanding, p.t_index)

    {p, _} =
      Enum.reduce(pending, {p, seq(p.a + 1 + p.t_index)}, fn bytes, {p, num} ->
        p =
          p
          |> telemetry(:retransmission, %{count: 1, bytes: byte_size(bytes)}, %{num: num})
          |> out(Frame.data(num, p.r, bytes))

        {p, seq(num + 1)}
      end)

    retransmitted = length(pending)

    p = %__MODULE__{
      p
      | t_index: length(p.outstanding),
        counters: Map.update!(p.counters, :retransmitted, &(&1 + retransmitted))
    }

    if retransmitted > 0, do: %__MODULE__{p | sack: false}, else: p
  end

  defp new_data(p) do
    if p.queue_len > 0 and length(p.outstanding) < p.window do
      {{:value, bytes}, queue} = :queue.out(p.queue)
      num = seq(n(p) + 1)

      p = %__MODULE__{
        p
        | queue: queue,
          queue_len: p.queue_len - 1,
          outstanding: p.outstanding ++ [bytes],
          t_index: p.t_index + 1,
          sack: false
      }

      p |> count(:sent) |> out(Frame.data(num, p.r, bytes)) |> new_data()
    else
      p
    end
  end

  defp ack(%__MODULE__{sack: true} = p), do: p |> out(Frame.ack(p.r)) |> put(:sack, false)
  defp ack(p), do: p

  # Output ---------------------------------------------------------------------------------------

  defp out(p, frame) do
    p = telemetry(p, :frame_sent, %{count: 1}, frame_meta(frame))
    %__MODULE__{p | out: [frame | p.out]}
  end

  defp emit(p, event), do: %__MODULE__{p | events: [event | p.events]}

  defp timer(p, name, ms_or_cancel), do: emit(p, {:timer, name, ms_or_cancel})

  defp telemetry(p, event, measurements, metadata),
    do: emit(p, {:telemetry, event, measurements, metadata})

  defp flush(p) do
    {%__MODULE__{p | out: [], events: []}, Enum.reverse(p.out), Enum.reverse(p.events)}
  end

  defp put(p, key, value), do: Map.put(p, key, value)

  defp frame_meta(%Data{num: num, resp: resp, data: bytes}),
    do: %{type: :data, num: num, resp: resp, bytes: byte_size(bytes)}

  defp frame_meta(%Control{type: type, subtype: subtype, rcvr: rcvr, sndr: sndr}),
    do: %{type: type, subtype: subtype, rcvr: rcvr, sndr: sndr}

  defp frame_meta(%Maintenance{data: bytes}), do: %{type: :maintenance, bytes: byte_size(bytes)}

  # Bookkeeping ----------------------------------------------------------------------------------

  defp n(p), do: seq(p.a + length(p.outstanding))

  defp seq(x), do: band(x, 0xFF)

  defp dist(from, to), do: band(to - from, 0xFF)

  # A < x <= N (or A <= x <= N), mod 256.
  defp in_range?(x, a, n, including_a) do
    d = dist(a, x)
    (d > 0 or including_a) and d <= dist(a, n)
  end

  defp count(p, counter),
    do: %__MODULE__{p | counters: Map.update!(p.counters, counter, &(&1 + 1))}

  defp count_error(p, %Error{reason: reason} = error) do
    p = %__MODULE__{p | last_error: {:receive, reason}}
    p = telemetry(p, :receive_error, %{count: 1}, %{reason: reason, num: error.num})

    case reason do
      :header_crc -> count(p, :header_crc_errors)
      :data_crc -> count(p, :data_crc_errors)
      _ -> count(p, :ignored)
    end
  end
end
