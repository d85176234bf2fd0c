defmodule Vws.Sim.Line.Schedule do
  @moduledoc """
  When the bytes of one direction of a simulated line come out: a fixed delay, a random jitter,
  and pacing at a baud rate. Pure: times are integers, microseconds of a monotonic clock, given
  by the caller; `Vws.Sim.Line` passes `System.monotonic_time(:microsecond)`.

    * `:delay` (ms, default 0) and `:jitter` (ms, default 0): bytes that enter at `t` are ready
      at `t + delay + j`, `j` drawn uniformly from `0..jitter` for each `push/3`. Bytes keep
      their order: a chunk is never ready before the one pushed ahead of it.
    * `:baud` (default nil: no pacing), with `:parity` (`:none`, `:even`, `:odd`) and
      `:stop_bits` (1 or 2): the line then carries `baud / bits_per_byte` bytes a second, a
      byte being a start bit, 8 data bits, the parity bit if any and the stop bits (10 bits for
      8N1, 11 with parity). A byte comes out of `take/2` only once its last bit has been sent:
      a byte whose transmission starts at `s` is out at `s + bits_per_byte / baud` seconds, and
      the next byte starts then, or when it is ready if later.
    * `:disconnect_rate` (cuts per second, default 0): `cut_interval/1` draws the time to the
      next cut of the line (exponentially distributed, so cuts come as a Poisson process).

  Jitter and cut intervals are drawn from a `:rand` state seeded from `:seed`.

      iex> s = Vws.Sim.Line.Schedule.new(baud: 9600)
      iex> Vws.Sim.Line.Schedule.bits_per_byte(s)
      10
      iex> Vws.Sim.Line.Schedule.transmit_us(s, 960)
      1_000_000
      iex> s = Vws.Sim.Line.Schedule.push(s, "ABC", 0)
      iex> {out, 1, next, s} = Vws.Sim.Line.Schedule.take(s, 2_000)
      iex> {IO.iodata_to_binary(out), next}
      {"A", 2084}
      iex> {out, 2, nil, _s} = Vws.Sim.Line.Schedule.take(s, 3_125)
      iex> IO.iodata_to_binary(out)
      "BC"
  """

  import Bitwise

  @keys [:delay, :jitter, :baud, :parity, :stop_bits, :disconnect_rate]
  @us_per_s 1_000_000

  @enforce_keys [:rand]
  defstruct delay: 0,
            jitter: 0,
            baud: nil,
            parity: :none,
            stop_bits: 1,
            disconnect_rate: 0.0,
            rand: nil,
            queue: nil,
            queued: 0,
            last_ready: nil,
            head_start: nil,
            head_sent: 0,
            line_free: nil,
            last_due: nil,
            clock: 0

  # queue: {ready_at, bytes} chunks, oldest first; queued: their bytes not yet taken. The head
  # chunk's transmission began at head_start, head_sent of its bytes are out. line_free: when the
  # last byte taken finished. clock: the latest time seen.
  @opaque t :: %__MODULE__{
            delay: non_neg_integer,
            jitter: non_neg_integer,
            baud: pos_integer | nil,
            parity: :none | :even | :odd,
            stop_bits: 1 | 2,
            disconnect_rate: float,
            rand: :rand.state(),
            queue: :queue.queue({integer, binary}),
            queued: non_neg_integer,
            last_ready: integer | nil,
            head_start: integer | nil,
            head_sent: non_neg_integer,
            line_free: integer | nil,
            clock: integer
          }

  @doc """
  A schedule. Options as in the moduledoc, and `:seed` (any term, default 0); other options are
  ignored. Raises `ArgumentError` on a value out of range.
  """
  @spec new(keyword) :: t
  def new(opts \\ []) do
    seed = :erlang.phash2(Keyword.get(opts, :seed, 0), 1 <<< 32)

    configure(
      %__MODULE__{rand: :rand.seed_s(:exsss, {seed, 0x071E, 3}), queue: :queue.new()},
      opts
    )
  end

  @doc """
  Changes the settings named in `opts`, keeping the others and what is queued. A new baud rate
  applies from the next byte.
  """
  @spec configure(t, keyword) :: t
  def configure(%__MODULE__{} = s, opts) do
    opts = Keyword.take(opts, @keys)
    s = if Keyword.has_key?(opts, :baud), do: restart_head(s), else: s
    Enum.reduce(opts, s, &set/2)
  end

  defp set({:delay, ms}, s) when is_integer(ms) and ms >= 0, do: %{s | delay: ms}
  defp set({:jitter, ms}, s) when is_integer(ms) and ms >= 0, do: %{s | jitter: ms}
  defp set({:baud, nil}, s), do: %{s | baud: nil}
  defp set({:baud, baud}, s) when is_integer(baud) and baud > 0, do: %{s | baud: baud}
  defp set({:parity, p}, s) when p in [:none, :even, :odd], do: %{s | parity: p}
  defp set({:stop_bits, n}, s) when n in [1, 2], do: %{s | stop_bits: n}

  defp set({:disconnect_rate, r}, s) when is_number(r) and r >= 0,
    do: %{s | disconnect_rate: r / 1}

  defp set({key, value}, _s),
    do: raise(ArgumentError, "line setting #{key}: #{inspect(value)} is out of range")

  # The bytes of the head chunk already out stay out; the rest waits for the line, which is
  # free from the latest time seen.
  defp restart_head(%{head_start: nil} = s), do: s

  defp restart_head(s) do
    {{:value, {ready, bytes}}, rest} = :queue.out(s.queue)
    left = binary_part(bytes, s.head_sent, byte_size(bytes) - s.head_sent)

    %{
      s
      | queue: :queue.in_r({ready, left}, rest),
        head_start: nil,
        head_sent: 0,
        line_free: max(s.line_free || s.clock, s.clock)
    }
  end

  @doc "The settings in force, as a keyword list `configure/2` accepts."
  @spec settings(t) :: keyword
  def settings(%__MODULE__{} = s) do
    [
      delay: s.delay,
      jitter: s.jitter,
      baud: s.baud,
      parity: s.parity,
      stop_bits: s.stop_bits,
      disconnect_rate: s.disconnect_rate
    ]
  end

  @doc "Bits on the wire per byte: start, 8 data bits, parity if any, stop bits."
  @spec bits_per_byte(t) :: pos_integer
  def bits_per_byte(%__MODULE__{parity: parity, stop_bits: stop}),
    do: 1 + 8 + if(parity == :none, do: 0, else: 1) + stop

  @doc "Microseconds the line takes to send `n` bytes back to back (rounded up; 0 unpaced)."
  @spec transmit_us(t, non_neg_integer) :: non_neg_integer
  def transmit_us(%__MODULE__{baud: nil}, _n), do: 0

  def transmit_us(%__MODULE__{baud: baud} = s, n),
    do: ceil_div(n * bits_per_byte(s) * @us_per_s, baud)

  @doc "Queues `bytes` entering the line at time `now`."
  @spec push(t, binary, integer) :: t
  def push(%__MODULE__{} = s, <<>>, now), do: %{s | clock: max(s.clock, now)}

  def push(%__MODULE__{} = s, bytes, now) when is_binary(bytes) do
    {jitter, rand} =
      if s.jitter > 0 do
        {u, rand} = :rand.uniform_real_s(s.rand)
        {trunc(u * (s.jitter * 1000 + 1)), rand}
      else
        {0, s.rand}
      end

    ready = max(now + s.delay * 1000 + jitter, s.last_ready || now)

    %{
      s
      | rand: rand,
        queue: :queue.in({ready, bytes}, s.queue),
        queued: s.queued + byte_size(bytes),
        last_ready: ready,
        clock: max(s.clock, now)
    }
  end

  @doc """
  Takes the bytes out of the line by time `now`: returns them (iodata), how many, the time the
  next byte is due (nil when nothing is queued), and the schedule.
  """
  @spec take(t, integer) :: {iodata, non_neg_integer, integer | nil, t}
  def take(%__MODULE__{} = s, now), do: take(%{s | clock: max(s.clock, now)}, now, [], 0)

  defp take(s, now, acc, count) do
    case :queue.peek(s.queue) do
      :empty ->
        {acc, count, nil, s}

      {:value, {ready, _bytes}} when ready > now ->
        {acc, count, ready, s}

      {:value, {_ready, bytes}} when s.baud == nil ->
        s = %{s | queue: :queue.drop(s.queue), queued: s.queued - byte_size(bytes)}
        take(s, now, [acc | bytes], count + byte_size(bytes))

      {:value, {ready, bytes}} ->
        paced(s, now, ready, bytes, acc, count)
    end
  end

  defp paced(s, now, ready, bytes, acc, count) do
    start = s.head_start || max(ready, s.line_free || ready)
    size = byte_size(bytes)
    bits = bits_per_byte(s) * @us_per_s
    # byte i (1-based) is out at start + ceil(i * bits / baud)
    done = if now < start, do: 0, else: min(size, div((now - start) * s.baud, bits))
    out = done - s.head_sent
    acc = if out > 0, do: [acc | binary_part(bytes, s.head_sent, out)], else: acc
    s = %{s | queued: s.queued - out}
    s = if out > 0, do: %{s | last_due: start + ceil_div(done * bits, s.baud)}, else: s

    if done == size do
      s = %{
        s
        | queue: :queue.drop(s.queue),
          head_start: nil,
          head_sent: 0,
          line_free: start + ceil_div(size * bits, s.baud)
      }

      take(s, now, acc, count + out)
    else
      next = start + ceil_div((done + 1) * bits, s.baud)
      {acc, count + out, next, %{s | head_start: start, head_sent: done}}
    end
  end

  @doc """
  When the last byte taken was due to be out (its last bit sent) on a paced line, or nil: what
  `take/2` gave out later than that was late by the caller's timer.
  """
  @spec last_due(t) :: integer | nil
  def last_due(%__MODULE__{last_due: due}), do: due

  @doc "Bytes queued and not yet taken."
  @spec queued(t) :: non_neg_integer
  def queued(%__MODULE__{queued: queued}), do: queued

  @doc """
  Draws the time to the next random cut of the line, in ms (`:infinity` with no
  `:disconnect_rate`).
  """
  @spec cut_interval(t) :: {non_neg_integer | :infinity, t}
  def cut_interval(%__MODULE__{disconnect_rate: rate} = s) when rate <= 0, do: {:infinity, s}

  def cut_interval(%__MODULE__{disconnect_rate: rate} = s) do
    {u, rand} = :rand.uniform_real_s(s.rand)
    {trunc(-:math.log(u) / rate * 1000), %{s | rand: rand}}
  end

  defp ceil_div(a, b), do: div(a + b - 1, b)
end
