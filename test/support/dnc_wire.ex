defmodule Vws.Test.DNCWire do
  @moduledoc """
  Two `Vws.Links.DNC.Session` cores back to back over an in-memory line, in simulated time: no process,
  no socket, no clock. `run/1` lets the CEC end (`:a`) make one request of the GE end (`:b`) and
  plays every byte and timer out to the end.

  Options:
    * `:command`, `:blocks` — the request
    * `:damage` — `fn direction, bytes, rand -> {bytes | :lost, rand}`: what the line does to a
      chunk going `:a_to_b` or `:b_to_a` (default: nothing)
    * `:seed` — for the damage's `:rand` state
    * `:answer` — the text blocks `:b` answers an R command with, or a function of what `:b`'s
      owner was handed so far and the blocks it ran, `fn received, ran -> blocks end` (a
      machine's status report)
    * `:then` — a second request `:a` makes as soon as the first has its reply (MONARCH's status
      report after a transmission); its result is `then_reply`
    * `:receive_buffer` — `:b`'s credit for an `E` reception; `:feed` — bytes a second `:b` runs of
      it (its buffer drains at that rate, giving credit back), default unlimited
    * `:latency_ms` — time a chunk takes on the line (1)
    * `:baud` — when given, a chunk also takes its characters' time at 10 bits a character
    * `:start_fill` — bytes `:b` buffers before it starts to run (0), as `Vws.Sim.GE2000` does
    * `:tick_ms` — the machine's step while it runs (default one character's time of `:feed`);
      `:max_steps` — a run that takes more events than this raises (200 000)

  The run goes on until nothing is on the line and no timer is armed (so a receiver that
  waits for an EOT the line lost times out).

  Returns `%{reply, received, blocks, time_ms, starved_ms, underruns, max_fill, counters}`: the
  request's result, what `:b`'s owner was handed (`{:received, command, blocks}` etc.), the
  blocks `:b` ran (an E reception), the simulated time (`drained_ms`: when the machine had run
  its buffer empty the last time), the time `:b`'s buffer was empty while
  an `E` reception was under way after its machine started, how often it ran empty so, the most
  its buffer held, and `:a`'s session counters.
  """

  alias Vws.Links.DNC.Session

  # the link's own defaults, as the link hands them to its core (asked at run time: read into an
  # attribute they would make this file recompile with the link and all it calls)
  def limits, do: Keyword.drop(Vws.Links.DNC.Link.defaults(), [:role, :owner, :endpoint])

  def run(opts) do
    buffer = Keyword.get(opts, :receive_buffer, :infinity)
    a = Session.new(role: :cec, limits: limits()) |> Session.connected()

    b =
      Session.new(role: :ge, limits: Keyword.put(limits(), :receive_buffer, buffer))
      |> Session.connected()

    w = %{
      now: 0,
      ends: %{a: %{s: a, timer: nil}, b: %{s: b, timer: nil}},
      # {deliver_at, seq, to, bytes}
      line: [],
      line_free: %{a_to_b: 0, b_to_a: 0},
      seq: 0,
      rand: :rand.seed_s(:exsss, {Keyword.get(opts, :seed, 1), 2, 3}),
      damage: Keyword.get(opts, :damage, fn _dir, bytes, rand -> {bytes, rand} end),
      answer: Keyword.get(opts, :answer, []),
      then: Keyword.get(opts, :then),
      then_reply: nil,
      latency: Keyword.get(opts, :latency_ms, 1),
      char_us: if(baud = opts[:baud], do: div(10 * 1_000_000, baud)),
      feed: Keyword.get(opts, :feed),
      start_fill: Keyword.get(opts, :start_fill, 0),
      running: false,
      tick: Keyword.get(opts, :tick_ms),
      max_steps: Keyword.get(opts, :max_steps, 200_000),
      underruns: 0,
      drained_ms: 0,
      reply: nil,
      received: [],
      ran: [],
      fill: 0,
      max_fill: 0,
      streaming: false,
      starved_ms: 0,
      steps: 0
    }

    result = Session.request(a, opts[:command], opts[:blocks], native(0))
    w = apply_result(w, :a, result)
    w = loop(w)

    %{
      reply: w.reply,
      then_reply: w.then_reply,
      received: Enum.reverse(w.received),
      blocks: Enum.reverse(w.ran),
      time_ms: w.now,
      starved_ms: w.starved_ms,
      underruns: w.underruns,
      drained_ms: w.drained_ms,
      max_fill: w.max_fill,
      counters: Session.counters(w.ends.a.s)
    }
  end

  defp loop(%{steps: steps, max_steps: max}) when steps > max,
    do: raise("the wire does not settle")

  defp loop(w) do
    next_line = Enum.min_by(w.line, &{elem(&1, 0), elem(&1, 1)}, fn -> nil end)
    timers = for {who, %{timer: {at, tag}}} <- w.ends, do: {at, who, tag}
    next_timer = Enum.min(timers, fn -> nil end)

    next_feed =
      if w.feed && w.fill > 0 && running?(w), do: w.now + (w.tick || max(div(1000, w.feed), 1))

    candidates =
      [
        next_line && {elem(next_line, 0), :line},
        next_timer && {elem(next_timer, 0), :timer},
        next_feed && {next_feed, :feed}
      ]
      |> Enum.reject(&is_nil/1)

    case candidates do
      [] ->
        w

      _ ->
        {at, kind} = Enum.min(candidates)
        w = advance(%{w | steps: w.steps + 1}, at)

        w =
          case kind do
            :line ->
              {_, _, to, bytes} = next_line
              w = %{w | line: List.delete(w.line, next_line)}
              apply_result(w, to, Session.handle_bytes(w.ends[to].s, bytes, native(w.now)))

            :timer ->
              {_, who, tag} = next_timer
              w = put_in(w.ends[who].timer, nil)
              apply_result(w, who, Session.handle_timeout(w.ends[who].s, tag, native(w.now)))

            :feed ->
              w
          end

        loop(w)
    end
  end

  # the machine runs its buffer at `feed` bytes a second (whole milliseconds of it)
  defp advance(w, at) do
    elapsed = at - w.now

    w =
      if w.streaming and w.running and w.fill == 0 and elapsed > 0,
        do: %{w | starved_ms: w.starved_ms + elapsed},
        else: w

    w = %{w | now: at, running: w.running or running?(w)}

    if w.feed && w.fill > 0 && w.running && elapsed > 0 do
      ran = min(w.fill, div(w.feed * at, 1000) - div(w.feed * (at - elapsed), 1000))
      b = Session.grant(w.ends.b.s, ran)
      w = put_in(%{w | fill: w.fill - ran}.ends.b.s, b)
      w = if w.fill == 0, do: %{w | drained_ms: at}, else: w
      # ran empty while the feed goes on: the machine dwells
      if w.fill == 0 and w.streaming, do: %{w | underruns: w.underruns + 1}, else: w
    else
      w
    end
  end

  # the machine runs once start_fill bytes are in (or the whole program: the feed ended)
  defp running?(w), do: w.running or w.fill >= w.start_fill or not w.streaming

  defp apply_result(w, who, {s, output, events}) do
    old = w.ends[who].s.state
    w = put_in(w.ends[who].s, s)
    w = if s.state != old, do: put_in(w.ends[who].timer, nil), else: w
    w = Enum.reduce(output, w, &transmit(&2, who, IO.iodata_to_binary(&1)))
    Enum.reduce(events, w, &event(&2, who, &1))
  end

  defp transmit(w, from, bytes) do
    dir = if from == :a, do: :a_to_b, else: :b_to_a
    to = if from == :a, do: :b, else: :a
    {bytes, rand} = w.damage.(dir, bytes, w.rand)
    w = %{w | rand: rand}

    case bytes do
      :lost ->
        w

      bytes ->
        at =
          if w.char_us do
            start = max(w.now, w.line_free[dir])
            done = start + div(byte_size(bytes) * w.char_us, 1000)
            done
          else
            w.now
          end

        w = if w.char_us, do: put_in(w.line_free[dir], at), else: w
        %{w | line: [{at + w.latency, w.seq, to, bytes} | w.line], seq: w.seq + 1}
    end
  end

  defp event(w, who, {:state_timeout, ms, tag}), do: put_in(w.ends[who].timer, {w.now + ms, tag})
  defp event(%{reply: nil, then: nil} = w, :a, {:reply, result}), do: %{w | reply: result}

  defp event(%{reply: nil} = w, :a, {:reply, result}) do
    w = %{w | reply: result}
    apply_result(w, :a, Session.request(w.ends.a.s, w.then, [], native(w.now)))
  end

  defp event(w, :a, {:reply, result}), do: %{w | then_reply: result}

  defp event(w, :b, {:notify, {:request, ref, _command, _blocks}}) do
    answer =
      if is_function(w.answer, 2),
        do: w.answer.(Enum.reverse(w.received), Enum.reverse(w.ran)),
        else: w.answer

    result = Session.answer(w.ends.b.s, ref, answer, native(w.now))
    apply_result(w, :b, result)
  end

  defp event(w, :b, {:notify, {:block, _command, _index, text}}) do
    fill = w.fill + byte_size(text)
    %{w | ran: [text | w.ran], fill: fill, max_fill: max(w.max_fill, fill), streaming: true}
  end

  defp event(w, :b, {:notify, {:received, _, _} = msg}),
    do: %{w | received: [msg | w.received], streaming: false, running: false}

  defp event(w, :b, {:notify, msg}), do: %{w | received: [msg | w.received]}
  defp event(w, _who, _other), do: w

  defp native(ms), do: System.convert_time_unit(ms, :millisecond, :native)
end
