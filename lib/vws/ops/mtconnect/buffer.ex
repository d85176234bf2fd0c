defmodule Vws.Ops.MTConnect.Buffer do
  @moduledoc """
  The agent's observations as MTConnect numbers them, as plain data (no process, no table): a
  circular buffer of the last `capacity` observations, each `{sequence, data_item_id, value,
  timestamp}`, and the state of every data item now and at checkpoints. `Vws.Ops.MTConnect.Agent`
  holds one and answers `current` and `sample` from it.

  Sequence numbers as the standard (and cppagent) gives them: the first observation is 1, each
  next one is one more; `firstSequence` is the oldest still held, `lastSequence` the newest,
  `nextSequence` the one the next observation gets. The buffer never holds more than `capacity`
  observations: the oldest falls out as a new one comes in, and `firstSequence` moves on.

  Every `checkpoint_frequency` observations the state of every data item is kept, so that the
  state at sequence `at` (`state_at/2`, `current?at=`) is built from the checkpoint before `at`
  and the observations after it; what fell out of the buffer is kept as the first checkpoint
  (each data item's last observation that left), so a state at `firstSequence` is whole.

      iex> alias Vws.Ops.MTConnect.Buffer
      iex> b = Buffer.new(2) |> Buffer.append("a", 1, 10) |> Buffer.append("b", 2, 20) |> Buffer.append("a", 3, 30)
      iex> Buffer.sequences(b)
      %{first: 2, last: 3, next: 4, size: 2}
      iex> Buffer.range(b, 1, 3)
      [{2, "b", 2, 20}, {3, "a", 3, 30}]
      iex> Buffer.state_at(b, 2)
      {:ok, %{"a" => {1, 1, 10}, "b" => {2, 2, 20}}}
      iex> Buffer.sample(b, 2, 1, nil)
      {:ok, [{2, "b", 2, 20}], 3}
      iex> Buffer.sample(b, 1, 1, nil)
      {:error, {:out_of_range, "from", 1, 2, 4}}
  """

  @enforce_keys [:capacity, :checkpoint_frequency, :ring]
  defstruct [
    :capacity,
    :checkpoint_frequency,
    :ring,
    first: 1,
    next: 1,
    current: %{},
    first_checkpoint: %{},
    checkpoints: %{}
  ]

  @typedoc "One observation: its sequence number, data item, value and time (µs)."
  @type observation :: {pos_integer, term, term, integer}
  @typedoc "The state of data items: each one's latest `{sequence, value, timestamp}`."
  @type state :: %{term => {pos_integer, term, integer}}
  @type t :: %__MODULE__{
          capacity: pos_integer,
          checkpoint_frequency: pos_integer,
          ring: :array.array(observation | nil),
          first: pos_integer,
          next: pos_integer,
          current: state,
          first_checkpoint: state,
          checkpoints: %{pos_integer => state}
        }
  @typedoc """
  A request out of range, as cppagent words it: the parameter, its value and the range it must
  be in; or a `count` of zero.
  """
  @type range_error ::
          {:out_of_range, String.t(), integer, integer, integer} | :zero_count

  @doc "An empty buffer of `capacity` observations, a checkpoint every `checkpoint_frequency`."
  @spec new(pos_integer, pos_integer) :: t
  def new(capacity, checkpoint_frequency \\ 1000)
      when is_integer(capacity) and capacity > 0 and is_integer(checkpoint_frequency) and
             checkpoint_frequency > 0 do
    %__MODULE__{
      capacity: capacity,
      checkpoint_frequency: checkpoint_frequency,
      ring: :array.new(size: capacity, fixed: true, default: nil)
    }
  end

  @doc "The sequence numbers: `%{first, last, next, size}` (`size` the capacity)."
  @spec sequences(t) :: %{
          first: pos_integer,
          last: non_neg_integer,
          next: pos_integer,
          size: pos_integer
        }
  def sequences(%__MODULE__{} = b),
    do: %{first: b.first, last: b.next - 1, next: b.next, size: b.capacity}

  @doc "The sequence number the next observation gets."
  @spec next(t) :: pos_integer
  def next(%__MODULE__{next: next}), do: next

  @doc "The latest value of a data item, or nil when it has none."
  @spec latest(t, term) :: term | nil
  def latest(%__MODULE__{current: current}, id) do
    case current do
      %{^id => {_seq, value, _ts}} -> value
      _ -> nil
    end
  end

  @doc "The state of every data item now: each one's latest `{sequence, value, timestamp}`."
  @spec current(t) :: state
  def current(%__MODULE__{current: current}), do: current

  @doc """
  Records an observation with the next sequence number; the oldest one falls out when the
  buffer is full.
  """
  @spec append(t, term, term, integer) :: t
  def append(%__MODULE__{} = b, id, value, ts) do
    seq = b.next
    current = Map.put(b.current, id, {seq, value, ts})
    # the slot's observation before this one: the oldest, when the buffer is full
    oldest = :array.get(slot(b, seq), b.ring)

    b = %{
      b
      | ring: :array.set(slot(b, seq), {seq, id, value, ts}, b.ring),
        current: current,
        next: seq + 1
    }

    b =
      if rem(seq, b.checkpoint_frequency) == 0,
        do: %{b | checkpoints: Map.put(b.checkpoints, seq, current)},
        else: b

    if b.next - b.first > b.capacity, do: drop_first(b, oldest), else: b
  end

  # The oldest observation falls out (its slot is the one just written over): the first
  # checkpoint keeps it as the state before the buffer.
  defp drop_first(b, {seq, id, value, ts}) do
    %{
      b
      | first: seq + 1,
        first_checkpoint: Map.put(b.first_checkpoint, id, {seq, value, ts}),
        checkpoints: Map.delete(b.checkpoints, seq)
    }
  end

  defp slot(b, seq), do: rem(seq, b.capacity)

  @doc "The observations held with sequence numbers from `from` to `to`, oldest first."
  @spec range(t, integer, integer) :: [observation]
  def range(%__MODULE__{} = b, from, to) do
    from = max(from, b.first)
    to = min(to, b.next - 1)
    if from > to, do: [], else: for(seq <- from..to, do: get(b, seq))
  end

  defp get(b, seq), do: :array.get(slot(b, seq), b.ring)

  @doc """
  The state of every data item just after sequence `at` (`current?at=`): `{:ok, state}`, or an
  error when `at` is not held (`firstSequence` to `lastSequence`).
  """
  @spec state_at(t, integer) :: {:ok, state} | {:error, range_error}
  def state_at(%__MODULE__{} = b, at) do
    if at < b.first or at >= b.next do
      {:error, {:out_of_range, "at", at, b.first, b.next - 1}}
    else
      c = div(at, b.checkpoint_frequency) * b.checkpoint_frequency

      {base, from} =
        case b.checkpoints do
          %{^c => checkpoint} when c >= b.first -> {checkpoint, c + 1}
          _ -> {b.first_checkpoint, b.first}
        end

      {:ok,
       Enum.reduce(range(b, from, at), base, fn {seq, id, value, ts}, acc ->
         Map.put(acc, id, {seq, value, ts})
       end)}
    end
  end

  @doc """
  The window of a `sample` request (`from`, `count`, `to`; nil when not given), among the
  observations `keep?` accepts (a device's or a path's): `{:ok, observations, next_sequence}`,
  or the error of the first parameter out of its range, as cppagent checks them:

    * `from` — `firstSequence` to `nextSequence` (default `firstSequence`);
    * `to` — after `from`, at most `nextSequence`: the last `count` observations up to `to`,
      `next_sequence` the one after `to`;
    * `count` — not 0, at most the capacity; negative (without `to`): the last `-count`
      observations up to `from` (default the newest), `next_sequence` the buffer's; positive:
      the first `count` from `from`, `next_sequence` the one after the last looked at (the
      buffer's when they run out).
  """
  @spec sample(t, integer | nil, integer, integer | nil, (observation -> boolean)) ::
          {:ok, [observation], pos_integer} | {:error, range_error}
  def sample(%__MODULE__{} = b, from, count, to, keep? \\ fn _ -> true end) do
    with :ok <- check_from(b, from),
         :ok <- check_to(b, from, to),
         :ok <- check_count(b, count, to) do
      cond do
        to != nil ->
          rows = b |> range(from || b.first, min(to, b.next - 1)) |> Enum.filter(keep?)
          {:ok, Enum.take(rows, -count), min(to + 1, b.next)}

        count > 0 ->
          forward(b, from || b.first, count, keep?, [], 0)

        true ->
          rows = b |> range(b.first, from || b.next - 1) |> Enum.filter(keep?)
          {:ok, Enum.take(rows, count), b.next}
      end
    end
  end

  # up to `count` kept observations from `seq`, and the sequence after the last one looked at
  defp forward(b, seq, _count, _keep?, acc, _n) when seq >= b.next,
    do: {:ok, Enum.reverse(acc), b.next}

  defp forward(b, seq, count, keep?, acc, n) do
    row = get(b, seq)

    cond do
      not keep?.(row) -> forward(b, seq + 1, count, keep?, acc, n)
      n + 1 == count -> {:ok, Enum.reverse([row | acc]), seq + 1}
      true -> forward(b, seq + 1, count, keep?, [row | acc], n + 1)
    end
  end

  defp check_from(_b, nil), do: :ok

  defp check_from(b, from) do
    if from < b.first or from > b.next,
      do: {:error, {:out_of_range, "from", from, b.first, b.next}},
      else: :ok
  end

  defp check_to(_b, _from, nil), do: :ok

  defp check_to(b, from, to) do
    lower = from || b.first

    if to <= lower or to > b.next,
      do: {:error, {:out_of_range, "to", to, lower + 1, b.next}},
      else: :ok
  end

  defp check_count(b, count, to) do
    lower = if to, do: 1, else: -b.capacity

    cond do
      count == 0 ->
        {:error, :zero_count}

      count < lower or count > b.capacity ->
        {:error, {:out_of_range, "count", count, lower, b.capacity}}

      true ->
        :ok
    end
  end
end
