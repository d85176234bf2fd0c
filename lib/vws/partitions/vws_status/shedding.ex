defmodule Vws.Partitions.VwsStatus.Shedding do
  @moduledoc """
  Load shedding for VWS_STATUS: when the node cannot make every workstation's poll of DAQ #1 on
  time, every workstation polls less often — all alike — down to a guaranteed minimum rate,
  instead of some polling on time and others not at all, and instead of the polls (which run
  at high priority) taking the CPU from the WC links and the partitions.

  The workstations of a **pool** (default `:node`: every VWS_STATUS of the node) share one
  *stretch* `k` ≥ 1: each polls every `k · poll_ms`. Each VWS_STATUS counts its due polls, the
  ones it made late (more than `:late_after_us` after their slot) and the ones it missed
  (`count/4`); the pool's governor (`start_link/1`, one per pool, started with the node for
  `:node`) reads and clears the counts every `:interval_ms` and sets the stretch by `next/3`.
  A poll counts late here when it starts more than half a period after its slot: the node
  could not get to it, where a poll a few ms late is only the OS waking a thread late.

    * more than `:high` (default 10 %) of the due polls late or missed: the stretch grows by
      half (at least by one), up to `:max_stretch`;
    * under `:low` (default 2 %) for `:calm` samples in a row (default 6, 3 s): it shrinks by
      one;
    * otherwise, or with no poll due, it stays.

  `:max_stretch` is `div(max_period_ms, poll_ms)` as VWS_STATUS applies it: a workstation polls
  at least every `:max_period_ms` (default 100 ms, five periods of the seed's 20 ms, half the
  200 ms after which its readings are shown stale). If the node cannot make even that, the polls
  go late or are missed and the readings go `NO DATA` after `stale_after_ms`, as without shedding:
  no reading is ever presented as fresher than it is, and a command awaiting a fresh reading
  (`Vws.Partitions.VwsStatus.await/4`) ends `ERROR` when none comes in its time.

  The pool's state is an `:atomics` array (stretch, held) and a `:counters` array (due, late,
  missed) kept in `:persistent_term` from the pool's creation: a poll reads one and adds to the
  other, nothing more. `hold/2` fixes the stretch (a benchmark, a test) until `release/1`.
  """
  use GenServer

  @defaults [interval_ms: 500, high: 0.10, low: 0.02, calm: 6, max_stretch: 5]

  @typedoc "The governor's memory between samples: the stretch and the calm samples in a row."
  @type state :: %{stretch: pos_integer, calm: non_neg_integer}
  @typedoc "What the polls of one interval did."
  @type sample :: %{due: non_neg_integer, late: non_neg_integer, missed: non_neg_integer}

  ## The policy (pure)

  @doc """
  The governor's next state after one interval's `sample`. Options `:high`, `:low`, `:calm`,
  `:max_stretch` as above.

      iex> alias Vws.Partitions.VwsStatus.Shedding
      iex> s = %{stretch: 1, calm: 0}
      iex> s = Shedding.next(s, %{due: 100, late: 30, missed: 0}, max_stretch: 5)
      iex> s.stretch
      2
      iex> Shedding.next(s, %{due: 100, late: 0, missed: 40}, max_stretch: 5).stretch
      3
  """
  @spec next(state, sample, keyword) :: state
  def next(%{stretch: stretch, calm: calm} = state, %{due: due} = sample, opts) do
    opts = Keyword.merge(@defaults, opts)
    max = Keyword.fetch!(opts, :max_stretch)
    bad = sample.late + sample.missed

    cond do
      due == 0 ->
        state

      bad > Keyword.fetch!(opts, :high) * due ->
        %{stretch: min(max, max(stretch + 1, ceil(stretch * 1.5))), calm: 0}

      bad < Keyword.fetch!(opts, :low) * due ->
        if calm + 1 >= Keyword.fetch!(opts, :calm),
          do: %{stretch: max(1, min(stretch, max) - 1), calm: 0},
          else: %{state | stretch: min(stretch, max), calm: calm + 1}

      true ->
        %{state | stretch: min(stretch, max), calm: 0}
    end
  end

  @doc """
  The period a workstation polls at under `stretch`: `stretch · poll_ms`, never longer than
  `max_period_ms` (nor shorter than `poll_ms`).

      iex> Vws.Partitions.VwsStatus.Shedding.period(20, 3, 100)
      60
      iex> Vws.Partitions.VwsStatus.Shedding.period(20, 9, 100)
      100
  """
  @spec period(pos_integer, pos_integer, pos_integer) :: pos_integer
  def period(poll_ms, stretch, max_period_ms),
    do: max(poll_ms, min(poll_ms * stretch, max(max_period_ms, poll_ms)))

  ## A pool's shared state

  @doc "Creates `pool`'s state if it has none (its stretch 1, not held)."
  @spec ensure_pool(term) :: :ok
  def ensure_pool(pool) do
    :global.trans({__MODULE__, pool}, fn ->
      if :persistent_term.get({__MODULE__, pool}, nil) == nil do
        stretch = :atomics.new(2, signed: false)
        :atomics.put(stretch, 1, 1)

        :persistent_term.put(
          {__MODULE__, pool},
          {stretch, :counters.new(3, [:write_concurrency])}
        )
      end
    end)

    :ok
  end

  @doc "The stretch of `pool` now: 1 for a pool that was never created."
  @spec stretch(term) :: pos_integer
  def stretch(pool) do
    case :persistent_term.get({__MODULE__, pool}, nil) do
      nil -> 1
      {atomics, _counters} -> :atomics.get(atomics, 1)
    end
  end

  @doc "Counts polls of one workstation: `due` slots, `late` of them made half a period late, `missed` not made."
  @spec count(term, non_neg_integer, non_neg_integer, non_neg_integer) :: :ok
  def count(pool, due, late, missed) do
    case :persistent_term.get({__MODULE__, pool}, nil) do
      nil ->
        :ok

      {_atomics, counters} ->
        :counters.add(counters, 1, due)
        :counters.add(counters, 2, late)
        :counters.add(counters, 3, missed)
    end
  end

  @doc "Fixes `pool`'s stretch at `stretch` until `release/1` (the governor leaves it alone)."
  @spec hold(term, pos_integer) :: :ok
  def hold(pool, stretch) when is_integer(stretch) and stretch >= 1 do
    :ok = ensure_pool(pool)
    {atomics, _} = :persistent_term.get({__MODULE__, pool})
    :atomics.put(atomics, 1, stretch)
    :atomics.put(atomics, 2, 1)
    :ok
  end

  @doc "Lets the governor set `pool`'s stretch again."
  @spec release(term) :: :ok
  def release(pool) do
    case :persistent_term.get({__MODULE__, pool}, nil) do
      nil -> :ok
      {atomics, _} -> :atomics.put(atomics, 2, 0)
    end
  end

  # the counts since the last take, cleared
  defp take(counters) do
    [due, late, missed] =
      for i <- 1..3 do
        n = :counters.get(counters, i)
        :counters.sub(counters, i, n)
        n
      end

    %{due: due, late: late, missed: missed}
  end

  ## The governor

  @doc false
  def child_spec(opts),
    do: %{
      id: {__MODULE__, Keyword.get(opts, :pool, :node)},
      start: {__MODULE__, :start_link, [opts]}
    }

  @doc """
  Starts the governor of `:pool` (default `:node`). Options: `:interval_ms` (default 500),
  `:high`, `:low`, `:calm`, `:max_stretch` (default 5) as in `next/3`.
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts), do: GenServer.start_link(__MODULE__, opts)

  @impl true
  def init(opts) do
    opts = Keyword.merge(@defaults, opts)
    pool = Keyword.get(opts, :pool, :node)
    :ok = ensure_pool(pool)
    {atomics, counters} = :persistent_term.get({__MODULE__, pool})

    s = %{
      pool: pool,
      opts: opts,
      atomics: atomics,
      counters: counters,
      state: %{stretch: 1, calm: 0}
    }

    {:ok, schedule(s)}
  end

  @impl true
  def handle_info(:sample, s) do
    sample = take(s.counters)

    s =
      if :atomics.get(s.atomics, 2) == 1 do
        %{s | state: %{stretch: :atomics.get(s.atomics, 1), calm: 0}}
      else
        state = next(s.state, sample, s.opts)

        if state.stretch != s.state.stretch do
          :atomics.put(s.atomics, 1, state.stretch)

          Vws.Telemetry.execute([:vws, :vws_status, :shedding], %{stretch: state.stretch}, %{
            pool: s.pool,
            due: sample.due,
            late: sample.late,
            missed: sample.missed
          })
        end

        %{s | state: state}
      end

    {:noreply, schedule(s)}
  end

  defp schedule(s) do
    Process.send_after(self(), :sample, Keyword.fetch!(s.opts, :interval_ms))
    s
  end
end
