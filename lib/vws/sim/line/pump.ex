defmodule Vws.Sim.Line.Pump do
  @moduledoc false
  # One direction of one connection through a Vws.Sim.Line: reads its source connection
  # (active-once), passes the bytes through the direction's Faults and Schedule, and sends them to
  # the destination when the schedule says they are out. A send that blocks (the far end does
  # not read) blocks this direction alone.
  #
  # Bounded: the source is re-armed only while fewer than max_queue bytes are queued, so at most
  # max_queue bytes plus one delivery are held. A transport that cannot hold bytes back (a tty)
  # may deliver while the queue is full; those bytes are lost and counted as an overrun, as in a
  # UART.
  #
  # It tells its session {:pump, self(), dir, event} with event :eof (the source closed and
  # everything before the close is out), {:error, reason} (the source failed; likewise drained),
  # {:cut, why} (disconnect_after reached and its bytes out, or a random cut) — each ends the
  # connection, and comes once — or {:dest_failed, reason}: a send failed, the destination has
  # gone, which the other direction will see as the end of its source.

  use GenServer

  alias Vws.Sim.Line.{Counters, Faults, Schedule}
  alias Vws.Links.Transport

  # Shortest wait between two deliveries while pacing: one character's time on the line, within
  # 1..10 ms — so a short reply (an acknowledgement) comes out when its last bit would, not up
  # to 10 ms late, which a stop-and-wait protocol pays on every block.
  @min_tick_us 1_000
  @max_tick_us 10_000

  def start_link(args), do: GenServer.start_link(__MODULE__, args)

  @doc false
  def go(pump), do: GenServer.cast(pump, :go)

  # Synchronous, so bytes sent after it returns meet the new faults; a pump stuck in a send to
  # a peer that does not read takes them when it gets free.
  @doc false
  def set_faults(pump, opts, timeout), do: call(pump, {:set_faults, opts}, timeout)

  defp call(pid, request, timeout) do
    GenServer.call(pid, request, timeout)
  catch
    :exit, _ -> :ok
  end

  @impl true
  def init(args) do
    # So that terminate/2 runs when the session stops it, and takes its bytes off the gauge.
    Process.flag(:trap_exit, true)
    opts = Keyword.put(args.faults, :seed, args.seed)

    state = %{
      session: args.session,
      dir: args.dir,
      source: args.source,
      dest: args.dest,
      counters: args.counters,
      max_queue: args.max_queue,
      faults: Faults.new(opts),
      schedule: Schedule.new(Keyword.put(opts, :seed, {:timing, args.seed})),
      armed: false,
      eof: nil,
      tick: nil,
      cut_timer: nil,
      reported: false,
      dest_failed: false,
      lateness: Map.get(args, :lateness),
      reply_slack: Map.get(args, :reply_slack, 0) * 1_000
    }

    {:ok, state}
  end

  @impl true
  def handle_cast(:go, state), do: {:noreply, state |> arm_random_cut() |> rearm()}

  @impl true
  def handle_call({:set_faults, opts}, _from, state) do
    state = %{
      state
      | faults: Faults.configure(state.faults, opts),
        schedule: Schedule.configure(state.schedule, opts)
    }

    state = if Keyword.has_key?(opts, :disconnect_rate), do: arm_random_cut(state), else: state
    {:reply, :ok, pump(state)}
  end

  @impl true
  def handle_info({:tick, tag}, %{tick: {tag, _timer, _at}} = state),
    do: {:noreply, pump(%{state | tick: nil})}

  def handle_info({:tick, _stale}, state), do: {:noreply, state}

  def handle_info({:random_cut, tag}, %{cut_timer: {tag, _timer}} = state),
    do: {:noreply, report(%{state | cut_timer: nil}, {:cut, :random})}

  def handle_info({:random_cut, _stale}, state), do: {:noreply, state}

  def handle_info(msg, state) do
    case Transport.handle_message(state.source, msg) do
      {:data, bytes} -> {:noreply, received(%{state | armed: false}, bytes)}
      :closed -> {:noreply, pump(%{state | armed: false, eof: :closed})}
      {:error, reason} -> {:noreply, pump(%{state | armed: false, eof: {:error, reason}})}
      :unknown -> {:noreply, state}
    end
  end

  @impl true
  def terminate(_reason, state) do
    Counters.add(state.counters, state.dir, :queued, -Schedule.queued(state.schedule))
  end

  defp received(%{eof: eof} = state, _bytes) when eof != nil, do: state

  defp received(state, bytes) do
    if Faults.cut?(state.faults) do
      state
    else
      if Schedule.queued(state.schedule) >= state.max_queue do
        Counters.add(state.counters, state.dir, :overruns, byte_size(bytes))
        rearm(state)
      else
        before = Faults.counters(state.faults)
        {out, faults} = Faults.apply(bytes, state.faults)
        Counters.add_faults(state.counters, state.dir, before, Faults.counters(faults))
        schedule = Schedule.push(state.schedule, out, reaction_time(state))
        Counters.add(state.counters, state.dir, :queued, byte_size(out))
        pump(%{state | faults: faults, schedule: schedule})
      end
    end
  end

  # Sends what is due, re-arms the source while there is room, reports the end once drained.
  defp pump(state) do
    now = now()
    {out, count, next, schedule} = Schedule.take(state.schedule, now)
    state = %{state | schedule: schedule}
    Counters.add(state.counters, state.dir, :queued, -count)

    if count > 0, do: note_lateness(state, now)

    state =
      if count > 0 do
        case Transport.send(state.dest, out) do
          :ok ->
            Counters.add(state.counters, state.dir, :bytes_out, count)
            state

          {:error, reason} ->
            dest_failed(state, reason)
        end
      else
        state
      end

    state |> tick(next, now) |> rearm() |> maybe_end()
  end

  defp tick(state, nil, _now), do: state

  defp tick(%{tick: {_tag, _timer, at}} = state, next, _now) when at <= next, do: state

  defp tick(state, next, now) do
    case state.tick do
      {_tag, timer, _at} -> Process.cancel_timer(timer)
      nil -> :ok
    end

    at = max(next, now + min_tick_us(state.schedule))
    tag = make_ref()
    timer = Process.send_after(self(), {:tick, tag}, div(at - now + 999, 1000))
    %{state | tick: {tag, timer, at}}
  end

  # A paced line is a model in time: bytes that came out of one direction late (our timer fired
  # late, the scheduler was busy) reached the far end late, so what the far end sends in reply
  # is taken to have started that much earlier — never before those bytes were due. Without
  # this every block of a stop-and-wait protocol would pay the machine's timer lateness twice.
  # The target's reply within `reply_slack` of its bytes coming out starts when they were due.
  # (atomics: due, lateness, delivered at — to_target in 1..3, to_client in 4..6)
  defp note_lateness(%{lateness: nil}, _now), do: :ok

  defp note_lateness(%{lateness: ref, schedule: schedule, dir: dir}, now) do
    case Schedule.last_due(schedule) do
      nil ->
        :ok

      due ->
        base = if dir == :to_target, do: 1, else: 4
        :atomics.put(ref, base, due)
        :atomics.put(ref, base + 1, max(now - due, 0))
        :atomics.put(ref, base + 2, now)
    end
  end

  defp reaction_time(%{lateness: nil}), do: now()

  defp reaction_time(%{lateness: ref, dir: dir, schedule: schedule} = state) do
    now = now()
    base = if dir == :to_target, do: 4, else: 1

    case {Schedule.settings(schedule)[:baud], :atomics.get(ref, base + 1)} do
      {nil, _} ->
        now

      {_baud, -1} ->
        now

      {_baud, late} ->
        due = :atomics.get(ref, base)

        if dir == :to_client and now - :atomics.get(ref, base + 2) <= state.reply_slack,
          do: due,
          else: max(now - late, due)
    end
  end

  defp min_tick_us(schedule) do
    case Schedule.settings(schedule)[:baud] do
      nil ->
        @max_tick_us

      baud ->
        char_us = div(Schedule.bits_per_byte(schedule) * 1_000_000, baud)
        char_us |> max(@min_tick_us) |> min(@max_tick_us)
    end
  end

  defp rearm(state) do
    if not state.armed and state.eof == nil and not Faults.cut?(state.faults) and
         Schedule.queued(state.schedule) < state.max_queue do
      # one delivery at a time: the bound above holds only if the source is held back
      Transport.activate_once(state.source)
      %{state | armed: true}
    else
      state
    end
  end

  defp maybe_end(state) do
    cond do
      Schedule.queued(state.schedule) > 0 -> state
      Faults.cut?(state.faults) -> report(state, {:cut, :after_bytes})
      state.eof == :closed -> report(state, :eof)
      state.eof != nil -> report(state, state.eof)
      true -> state
    end
  end

  defp arm_random_cut(state) do
    with {_tag, timer} <- state.cut_timer, do: Process.cancel_timer(timer)
    {ms, schedule} = Schedule.cut_interval(state.schedule)
    state = %{state | schedule: schedule, cut_timer: nil}

    case ms do
      :infinity ->
        state

      ms ->
        tag = make_ref()
        %{state | cut_timer: {tag, Process.send_after(self(), {:random_cut, tag}, ms)}}
    end
  end

  # One end report per pump: the session ends the connection on the first.
  defp report(%{reported: true} = state, _event), do: state

  defp report(state, event) do
    send(state.session, {:pump, self(), state.dir, event})
    %{state | reported: true}
  end

  defp dest_failed(%{dest_failed: true} = state, _reason), do: state

  defp dest_failed(state, reason) do
    send(state.session, {:pump, self(), state.dir, {:dest_failed, reason}})
    %{state | dest_failed: true}
  end

  defp now, do: System.monotonic_time(:microsecond)
end
