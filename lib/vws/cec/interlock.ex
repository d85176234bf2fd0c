defmodule Vws.CEC.Interlock do
  @moduledoc """
  The software safety interlocks of seed §2.3.8: exclusive access to a work volume as a lease
  kept in the workstation's mailboxes, taken by the seed's M1/M2 procedure.

      iex> ws = "interlock-doc"
      iex> {:ok, _} = Vws.CEC.Mailbox.Owner.start_link(workstation: ws)
      iex> Vws.CEC.Interlock.acquire(ws, :tray1, :robot, 0)
      :ok
      iex> Vws.CEC.Interlock.acquire(ws, :tray1, :mhs, 0)
      {:error, "INTERLOCK TRAY1 HELD BY ROBOT"}
      iex> Vws.CEC.Interlock.acquire(ws, :table, :fixture, 0)
      :ok
      iex> Vws.CEC.Interlock.acquire(ws, :table, :robot, 0)
      :ok
      iex> Vws.CEC.Interlock.acquire(ws, :table, :monarch, 0)
      {:error, "INTERLOCK TABLE HELD BY FIXTURE"}
      iex> Vws.CEC.Interlock.release(ws, :table, :fixture)
      :ok
      iex> Vws.CEC.Interlock.holders(ws, :table)
      [:robot]

  ## The procedure (seed §2.3.8, [MAG1])

  Two operations A1 and A2 that must never run together each have a mailbox, M1 and M2. To
  start A1 a program writes F1 into M1, *then* reads M2; if F2 says A2 is in progress it
  withdraws F1, pauses, and tries again, about four times a second, until A1 may start or the
  request times out. Because each side writes before it reads, the two can never both go ahead.

  Here each holder of a volume has its own mailbox, the key `{:interlock, volume, holder}` of
  the workstation's mailbox table. `acquire/5` posts the holder's request with `:ets.insert_new`
  (atomic), reads the entries of every holder it must exclude, and — with its own request still
  posted — runs the caller's physical `:check` (the conditions of the rule: machine idle, table
  parked …). If nothing is in the way the request becomes the lease; else the request is
  withdrawn and tried again when a lease on the volume ends (`release/4` causes the
  workstation's `:interlock` event, which the waiting requester is subscribed to) and at the
  latest every `:retry_ms` (default 250, with a little jitter so that two requesters cannot stay
  in step; the conditions of the check change without an event) until `timeout` ms have passed, and the call ends
  `{:error, "INTERLOCK <VOLUME> HELD BY <HOLDER>"}` or `{:error, "INTERLOCK <VOLUME> <why>"}`
  with what the check read last.

  ## Volumes and holders

  | volume | who may share it | excluded |
  |--------|------------------|----------|
  | `:table` — the machine table with the vise and the pallet | the CEC's users of the table: `:robot` (rule 1a) and `:fixture` (3a) | `:monarch`'s cycle (1b, 3b) |
  | `:tray1`, `:tray2` — the roller tables | nobody | `:robot` (2a) against `:mhs` (2b) |

  The robot and the vise work the table together (the robot holds a part in the vise while the
  vise closes on it), but neither may while the machine holds it, nor the machine while either
  does. Any other volume or holder is exclusive.

  ## Reasons

  One holder may hold a volume for several reasons at once — ROBOT for a `DISABLE_TABLE` and
  because the arm is in the volume; FIXTURE for a `DISABLE_TABLE` and for a vise motion under
  way. `acquire/5` adds its `:as` reason (default `:lease`), `release/4` removes one, and the
  lease ends when no reason is left (`release/3` removes them all).

  ## Telemetry

  `[:vws, :interlock, :acquired]` and `[:vws, :interlock, :refused]` with `wait_ms` and `tries`
  (metadata `workstation, volume, holder, reason`, and `why` when refused);
  `[:vws, :interlock, :released]` (see `Vws.Telemetry`).

  ## Durability and visibility

  The leases live in the mailbox table, owned by `Vws.CEC.Mailbox.Owner`: a partition that crashes
  and restarts finds its leases where it left them (the arm is still in the volume). With a
  journal (`Vws.CEC.Journal`) every lease and every change of its reasons is written to disk before
  it counts, and a workstation — or node — that restarts holds what it held: the arm that was in
  the vise when the node died is still there, and no cycle may start. A request
  left posted by a process that died in the middle of `acquire/5` is recognised as dead and
  cleared by the next requester. `held/1` lists the leases for iex and the dashboard.
  """

  require Logger

  alias Vws.CEC.Mailbox

  @type volume :: :table | :tray1 | :tray2 | atom
  @type holder :: :robot | :fixture | :monarch | :mhs | atom
  @type lease :: %{
          volume: volume,
          holder: holder,
          reasons: [atom],
          since_ms: integer,
          age_ms: non_neg_integer
        }

  # holders that may hold a volume at the same time; everyone else excludes everyone else
  @shared %{table: [[:robot, :fixture]]}

  @retry_ms 250

  @doc """
  Takes `volume` for `holder` by the M1/M2 procedure (see the moduledoc), trying again every
  `:retry_ms` until `timeout` ms have passed (`0`: one try). Options:

    * `:as` — the reason the lease is held for (default `:lease`), see "Reasons";
    * `:check` — `(-> :ok | {:error, why})`, the rule's physical conditions, run while the
      request is posted; `why` reads after `INTERLOCK <VOLUME> ` (`"MACHINE ACTIVE"`);
    * `:retry_ms` — the pause between tries (default 250: four times a second);
    * `:clock` — `{now, pause}`: the time the tries are counted in, `now.()` in ms and
      `pause.(ms)` to let `ms` pass (tests run the retries on simulated time with it). Default:
      the monotonic clock, and a pause that a lease ending cuts short.

  A holder that already holds the volume keeps it and only runs the check. Returns `:ok`, or
  `{:error, "INTERLOCK <VOLUME> HELD BY <HOLDER>" | "INTERLOCK <VOLUME> <why>"}`.
  """
  @spec acquire(Mailbox.workstation(), volume, holder, non_neg_integer, keyword) ::
          :ok | {:error, String.t()}
  def acquire(ws, volume, holder, timeout, opts \\ []) do
    clock = Keyword.get(opts, :clock, {&now/0, nil})
    {clock_now, _pause} = clock
    started = clock_now.()

    config = %{
      workstation: ws,
      clock: clock,
      started: started,
      tries: 1,
      table: Mailbox.table(ws),
      volume: volume,
      holder: holder,
      as: Keyword.get(opts, :as, :lease),
      check: Keyword.get(opts, :check, fn -> :ok end),
      retry_ms: Keyword.get(opts, :retry_ms, @retry_ms),
      deadline: started + timeout
    }

    if timeout > 0 do
      # woken by a lease that ends (release/4) instead of only by the next try
      Vws.CEC.Events.create(ws, :interlock)
      :ok = Vws.CEC.Events.subscribe(ws, :interlock)

      try do
        try_acquire(config)
      after
        Vws.CEC.Events.unsubscribe(ws, :interlock)
        flush_releases(ws)
      end
    else
      try_acquire(config)
    end
  end

  defp flush_releases(ws) do
    receive do
      {:vws_event, ^ws, :interlock, _volume} -> flush_releases(ws)
    after
      0 -> :ok
    end
  end

  defp try_acquire(c) do
    key = key(c.volume, c.holder)

    result =
      case :ets.lookup(c.table, key) do
        [{^key, %{state: :held} = lease}] ->
          # ours already: only the conditions of this use are read
          reasons = add(lease.reasons, c.as)

          with :ok <- check(c),
               :ok <- if(reasons == lease.reasons, do: :ok, else: journal(c, reasons)) do
            :ets.insert(c.table, {key, %{lease | reasons: reasons}})
            :ok
          end

        _none_or_dead_request ->
          clear_dead_request(c.table, key)

          request = %{
            state: :requesting,
            pid: self(),
            since: now(),
            order: System.unique_integer([:monotonic]),
            reasons: [c.as]
          }

          # F1 into M1 …
          if :ets.insert_new(c.table, {key, request}) do
            # … then M2, and the conditions, with F1 still posted
            outcome =
              case in_the_way(c.table, c.volume, c.holder) do
                [] ->
                  with :ok <- check(c), do: journal(c, request.reasons)

                [other | _] ->
                  {:error, "HELD BY " <> name(other)}
              end

            if outcome == :ok do
              :ets.insert(c.table, {key, %{request | state: :held}})
              :ok
            else
              # F1 withdrawn
              :ets.delete_object(c.table, {key, request})
              outcome
            end
          else
            {:error, "HELD BY " <> name(c.holder)}
          end
      end

    case result do
      :ok ->
        emit(:acquired, c, %{})
        :ok

      {:error, why} ->
        left = c.deadline - clock_now(c)

        if left <= 0 do
          emit(:refused, c, %{why: why})
          {:error, "INTERLOCK #{name(c.volume)} #{why}"}
        else
          await_release(c, min(left, jitter(c.retry_ms)))
          try_acquire(%{c | tries: c.tries + 1})
        end
    end
  end

  # Until a lease on the volume ends (the event release/4 causes) or `ms` pass: the conditions
  # of `:check` (the machine idle, the table parked) change without an event, so they are read
  # again at every try, four times a second as in the seed.
  defp await_release(%{workstation: ws, volume: volume, clock: {_now, pause}}, ms) do
    receive do
      {:vws_event, ^ws, :interlock, ^volume} -> :ok
    after
      if(pause, do: 0, else: ms) -> if pause, do: pause.(ms), else: :ok
    end
  end

  defp clock_now(%{clock: {now, _pause}}), do: now.()

  defp emit(event, c, meta) do
    Vws.Telemetry.execute(
      [:vws, :interlock, event],
      %{wait_ms: clock_now(c) - c.started, tries: c.tries},
      Map.merge(
        %{workstation: c.workstation, volume: c.volume, holder: c.holder, reason: c.as},
        meta
      )
    )
  end

  defp check(c) do
    case c.check.() do
      :ok -> :ok
      {:error, why} when is_binary(why) -> {:error, why}
    end
  end

  # The holders whose entries (lease or posted request) exclude `holder` from `volume`, the
  # earliest first.
  defp in_the_way(table, volume, holder) do
    for {{:interlock, ^volume, other} = key, entry} <-
          :ets.match_object(table, {{:interlock, volume, :_}, :_}),
        other != holder,
        not compatible?(volume, holder, other),
        not dead_request?(table, key, entry) do
      {entry.order, other}
    end
    |> Enum.sort()
    |> Enum.map(&elem(&1, 1))
  end

  defp dead_request?(table, key, %{state: :requesting, pid: pid} = entry) do
    if Process.alive?(pid) do
      false
    else
      :ets.delete_object(table, {key, entry})
      true
    end
  end

  defp dead_request?(_table, _key, _entry), do: false

  defp clear_dead_request(table, key) do
    case :ets.lookup(table, key) do
      [{^key, entry}] -> dead_request?(table, key, entry)
      [] -> false
    end
  end

  @doc "True when two holders may hold `volume` at the same time."
  @spec compatible?(volume, holder, holder) :: boolean
  def compatible?(volume, a, b) do
    a == b or Enum.any?(Map.get(@shared, volume, []), &(a in &1 and b in &1))
  end

  @doc """
  Gives up `reason` of `holder`'s lease on `volume` (`:all`: every reason); the lease ends
  when no reason is left. Releasing what is not held is fine. Returns `:ok`.
  """
  @spec release(Mailbox.workstation(), volume, holder, atom) :: :ok
  def release(ws, volume, holder, reason \\ :all) do
    table = Mailbox.table(ws)
    key = key(volume, holder)

    case :ets.lookup(table, key) do
      [{^key, %{state: :held} = lease}] ->
        reasons = if(reason == :all, do: [], else: List.delete(lease.reasons, reason))
        # not durable: the restarted workstation holds the lease still, which is the safe side
        _ = journal(%{table: table, volume: volume, holder: holder}, reasons)

        case reasons do
          [] ->
            :ets.delete_object(table, {key, lease})
            # wakes the requesters waiting in acquire/5 (an event never created: none wait)
            _ = Vws.CEC.Events.cause(ws, :interlock, volume)

          reasons ->
            :ets.insert(table, {key, %{lease | reasons: reasons}})
        end

        Vws.Telemetry.execute([:vws, :interlock, :released], %{count: 1}, %{
          workstation: ws,
          volume: volume,
          holder: holder,
          reason: reason
        })

      _ ->
        :ok
    end

    :ok
  end

  @doc "True when `holder` holds `volume` (for `reason`, when given)."
  @spec holds?(Mailbox.workstation(), volume, holder, atom | nil) :: boolean
  def holds?(ws, volume, holder, reason \\ nil) do
    case :ets.lookup(Mailbox.table(ws), key(volume, holder)) do
      [{_, %{state: :held, reasons: reasons}}] -> reason == nil or reason in reasons
      _ -> false
    end
  end

  @doc "Who holds `volume`, the earliest first (the table may have two holders)."
  @spec holders(Mailbox.workstation(), volume) :: [holder]
  def holders(ws, volume) do
    ws |> held() |> Enum.filter(&(&1.volume == volume)) |> Enum.map(& &1.holder)
  end

  @doc "The holder of `volume` (the earliest, when it is shared), or nil when it is free."
  @spec holder(Mailbox.workstation(), volume) :: holder | nil
  def holder(ws, volume), do: ws |> holders(volume) |> List.first()

  @doc """
  Every lease of a workstation, by volume and then the earliest first:
  `[%{volume, holder, reasons, since_ms, age_ms}]` (requests being tried are not leases).
  """
  @spec held(Mailbox.workstation()) :: [lease]
  def held(ws) do
    now = now()

    for {{:interlock, volume, holder}, %{state: :held} = lease} <-
          :ets.match_object(Mailbox.table(ws), {{:interlock, :_, :_}, :_}) do
      {lease.order,
       %{
         volume: volume,
         holder: holder,
         reasons: lease.reasons,
         since_ms: lease.since,
         age_ms: now - lease.since
       }}
    end
    |> Enum.sort_by(fn {order, lease} -> {to_string(lease.volume), order} end)
    |> Enum.map(&elem(&1, 1))
  end

  ## Helpers

  @doc "The name of a volume or holder as an error text shows it: `:tray1` → `TRAY1`."
  @spec name(atom) :: String.t()
  def name(atom), do: atom |> to_string() |> String.upcase()

  defp key(volume, holder), do: {:interlock, volume, holder}

  # Durable before it counts (`Vws.CEC.Journal`, when the workstation has one): a lease written
  # with its reasons, `[]` when it ends. A lease that cannot be made durable is not granted.
  defp journal(%{table: table, volume: volume, holder: holder}, reasons) do
    case Mailbox.record(table, {:lease, volume, holder, reasons}) do
      :ok ->
        :ok

      {:error, reason} ->
        Logger.error("journal write failed (#{inspect(reason)}): lease #{volume} #{holder}")
        {:error, "NOT DURABLE (JOURNAL WRITE FAILED)"}
    end
  end

  @doc """
  The held leases of a mailbox table as `[{volume, holder, reasons}]`, the earliest first: what
  the journal (`Vws.CEC.Journal`) keeps of them.
  """
  @spec leases(:ets.tid()) :: [{volume, holder, [atom]}]
  def leases(table) do
    for {{:interlock, volume, holder}, %{state: :held} = lease} <-
          :ets.match_object(table, {{:interlock, :_, :_}, :_}) do
      {lease.order, {volume, holder, lease.reasons}}
    end
    |> Enum.sort()
    |> Enum.map(&elem(&1, 1))
  end

  @doc """
  Puts back leases the journal restored after a restart (`leases/1`'s form), in that order:
  held, for their reasons, by no process of this life of the workstation.
  """
  @spec restore(:ets.tid(), [{volume, holder, [atom]}]) :: :ok
  def restore(table, leases) do
    for {volume, holder, reasons} <- leases do
      lease = %{
        state: :held,
        pid: nil,
        since: now(),
        order: System.unique_integer([:monotonic]),
        reasons: reasons
      }

      :ets.insert(table, {key(volume, holder), lease})
    end

    :ok
  end

  defp add(reasons, reason), do: if(reason in reasons, do: reasons, else: reasons ++ [reason])

  defp jitter(ms) when ms <= 1, do: max(ms, 0)
  defp jitter(ms), do: ms - div(ms, 5) + :rand.uniform(div(ms, 5) * 2 + 1) - 1

  defp now, do: System.monotonic_time(:millisecond)
end
