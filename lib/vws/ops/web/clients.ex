defmodule Vws.Ops.Web.Clients do
  @moduledoc false
  # Who holds the connections of `Vws.Ops.Web.Server`, and what each is doing: the admission
  # control that gives every client (peer address; an IPv6 client by its /64) its own share.
  #
  # One process decides every admission (the acceptors call `admit/3`), so the counts are exact.
  # A public ETS table holds one row per open connection, `{pid, client, state, since}`, where
  # `state` is `:idle` (waiting for a request's head: a new connection, a kept-alive one between
  # requests, and one that trickles its head), `:busy` (a request being answered) or `:stream`,
  # and `since` (µs, monotonic) when it entered that state; each connection sets its own row
  # (`mark/2`). A second table, ordered, indexes the idle ones by `{since, pid}`, so the one idle
  # the longest — of all, or of one client — is found without a scan: admission stays cheap
  # while the server is full and hostile clients come and go (every such newcomer closes one). A new connection is admitted when the client holds fewer than
  # `max_client_connections` and the server fewer than `max_connections`; otherwise room is made
  # by closing, in this order:
  #
  #   1. the client's own connection idle the longest, when the client is at its share;
  #   2. the connection idle the longest of any client, when the server is full;
  #   3. the oldest stream of the client holding the most connections, when the server is full,
  #      no connection is idle, and that client holds more than the newcomer would;
  #
  # and only when none can be closed is the newcomer refused (503). A closed connection's process
  # is killed, which closes its socket; its row goes at once.
  #
  # Before all that, while the server holds half its connections or more, each client may open at
  # most `max_client_connect_rate` connections a second (with a burst of two seconds' worth):
  # beyond it a newcomer is refused at once, closing nobody. A client that reconnects as fast as it is closed — idle sockets coming back — so
  # costs the server a bounded amount of work, and cannot close the others' connections faster.
  #
  # Each client also has its own request pace (`pace/1`): an :atomics cell holding the time from
  # which its next request may be served. It outlives the client's connections until that time
  # has passed (swept every 5 s), so closing and reconnecting does not reset it.
  use GenServer

  @sweep 5_000

  @spec start_link(map) :: GenServer.on_start()
  def start_link(limits), do: GenServer.start_link(__MODULE__, limits)

  @doc false
  # Admits a connection from `client` and starts its process with `start` (a function answering
  # `{:ok, pid}` or an error): `{:ok, pid, pace, idle_key}` (`pace`: the client's pace cell; `idle_key`: its entry in the idle index, for `adopt/1`), or
  # `{:refuse, why}` (`:client` at its share, `:rate` opening too fast, `:full`), or `{:error, reason}` from `start`.
  def admit(clients, client, start), do: GenServer.call(clients, {:admit, client, start}, 30_000)

  @doc false
  # The tables of connections and of idle ones (for `mark/3`).
  def tables(clients), do: GenServer.call(clients, :tables)

  @doc false
  # How many connections are open: all, and per client.
  def count(clients), do: GenServer.call(clients, :count)

  @doc false
  # The calling connection is now `state` (:idle, :busy, :stream). Its idle index key, if any, is
  # kept in its process dictionary.
  def mark({table, idle}, state) do
    t = now()

    case Process.delete(:vws_web_idle) do
      nil -> :ok
      key -> :ets.delete(idle, key)
    end

    with true <- :ets.update_element(table, self(), [{3, state}, {4, t}]),
         :idle <- state,
         [{_, client, _, _}] <- :ets.lookup(table, self()) do
      :ets.insert(idle, {{t, self()}, client})
      Process.put(:vws_web_idle, {t, self()})
    end

    :ok
  end

  @doc false
  # A new connection's own idle key (set by `admit/3`), for `mark/3` to delete.
  def adopt(key), do: Process.put(:vws_web_idle, key)

  @doc false
  # The client of a peer address: an IPv4 address itself, an IPv6 address by its /64 (a host is
  # given a /64 and may use any address of it).
  def client({_, _, _, _} = ip), do: ip
  def client({0, 0, 0, 0, 0, 0xFFFF, _, _} = ip), do: ip
  def client({a, b, c, d, _, _, _, _}), do: {a, b, c, d, 0, 0, 0, 0}

  @doc false
  # Takes the next free slot of a pace cell (1/rate s apart) and waits for it; `:busy` when it is
  # more than `max_wait` ms away (then nothing is taken; the server's `:max_wait` limit).
  # `burst`: how many slots a client that was quiet may take at once (the cell's time may lag
  # that far behind now).
  def pace(ref, rate, max_wait, burst \\ 0) do
    interval = div(1_000_000, rate)
    now = System.monotonic_time(:microsecond)
    next = :atomics.get(ref, 1)
    slot = max(next, now - burst * interval)

    cond do
      slot - now > max_wait * 1000 ->
        :busy

      :atomics.compare_exchange(ref, 1, next, slot + interval) == :ok ->
        wait = div(slot - now, 1000)
        if wait > 0, do: Process.sleep(wait)
        :ok

      true ->
        pace(ref, rate, max_wait, burst)
    end
  end

  @doc false
  # A pace cell whose next slot is now, plus `offset` µs (monotonic time may be negative: it
  # starts at now, not 0).
  def pace_cell(offset \\ 0) do
    ref = :atomics.new(1, signed: true)
    :atomics.put(ref, 1, System.monotonic_time(:microsecond) + offset)
    ref
  end

  @impl true
  def init(limits) do
    # HTTP work yields to the workstations (Vws.Ops.Web.Server's moduledoc)
    Process.flag(:priority, :low)
    table = :ets.new(__MODULE__, [:set, :public, write_concurrency: true, read_concurrency: true])
    idle = :ets.new(__MODULE__, [:ordered_set, :public, write_concurrency: true])
    Process.send_after(self(), :sweep, @sweep)

    {:ok,
     %{
       table: table,
       idle: idle,
       max: limits.max_connections,
       per_client: limits.max_client_connections,
       connect_interval: div(1_000_000, limits.max_client_connect_rate),
       total: 0,
       # client => %{count: n, pace: atomics, connect: µs from which it may open the next}
       clients: %{}
     }}
  end

  @impl true
  def handle_call({:admit, client, start}, _from, s) do
    now_us = System.monotonic_time(:microsecond)
    # (monotonic time may be negative: a new client starts with its full burst, from now)
    entry =
      Map.get_lazy(s.clients, client, fn ->
        # a new client starts with its full bursts: a second's requests, two seconds' connections
        %{count: 0, pace: pace_cell(-1_000_000), connect: now_us - 2_000_000}
      end)

    # two seconds' worth of connections at once, then one per interval
    slot = max(entry.connect, now_us - 2 * 1_000_000)

    cond do
      slot <= now_us ->
        entry = %{entry | connect: slot + s.connect_interval}
        admit(%{s | clients: Map.put(s.clients, client, entry)}, client, entry, start)

      # only while the server holds half its connections or more: until then, reconnecting
      # costs nobody anything
      s.total * 2 >= s.max ->
        {:reply, {:refuse, :rate}, %{s | clients: Map.put(s.clients, client, entry)}}

      true ->
        admit(%{s | clients: Map.put(s.clients, client, entry)}, client, entry, start)
    end
  end

  def handle_call(:tables, _from, s), do: {:reply, {s.table, s.idle}, s}

  def handle_call(:count, _from, s) do
    per = for {c, %{count: n}} <- s.clients, n > 0, into: %{}, do: {c, n}
    {:reply, {s.total, per}, s}
  end

  defp admit(s, client, entry, start) do
    case make_room(s, client, entry.count) do
      {:ok, s} ->
        case start.() do
          {:ok, pid} ->
            Process.monitor(pid)
            t = now()
            :ets.insert(s.table, {pid, client, :idle, t})
            :ets.insert(s.idle, {{t, pid}, client})
            {:reply, {:ok, pid, entry.pace, {t, pid}}, add(s, client, 1)}

          {:error, _} = error ->
            {:reply, error, s}
        end

      {:refuse, why} ->
        {:reply, {:refuse, why}, s}
    end
  end

  @impl true
  def handle_info({:DOWN, _ref, :process, pid, _reason}, s) do
    case :ets.take(s.table, pid) do
      [{^pid, client, state, since}] ->
        if state == :idle, do: :ets.delete(s.idle, {since, pid})
        {:noreply, add(s, client, -1)}

      [] ->
        {:noreply, s}
    end
  end

  def handle_info(:sweep, s) do
    Process.send_after(self(), :sweep, @sweep)
    now_us = System.monotonic_time(:microsecond)

    clients =
      s.clients
      |> Enum.reject(fn {_c, e} ->
        e.count == 0 and :atomics.get(e.pace, 1) <= now_us and e.connect <= now_us
      end)
      |> Map.new()

    {:noreply, %{s | clients: clients}}
  end

  def handle_info(_msg, s), do: {:noreply, s}

  defp add(s, client, n) do
    clients = Map.update!(s.clients, client, &%{&1 | count: &1.count + n})
    %{s | clients: clients, total: s.total + n}
  end

  # Room for one more connection of `client` (holding `held`), closing others if need be.
  defp make_room(s, client, held) do
    cond do
      held >= s.per_client ->
        case oldest_idle(s, client) do
          nil -> {:refuse, :client}
          victim -> {:ok, shed(s, victim)}
        end

      s.total >= s.max ->
        with nil <- oldest_idle(s, :_),
             nil <- heaviest_stream(s, held) do
          {:refuse, :full}
        else
          victim -> {:ok, shed(s, victim)}
        end

      true ->
        {:ok, s}
    end
  end

  # The connection of `client` (:_ for any) idle the longest: the first of the ordered index that
  # is still idle (an entry may be stale: a connection that just left idle, or died).
  defp oldest_idle(s, client) do
    case :ets.select(s.idle, [{{:"$1", client}, [], [:"$1"]}], 1) do
      {[{since, pid} = key], _} ->
        case :ets.lookup(s.table, pid) do
          [{^pid, _, :idle, ^since}] ->
            pid

          _ ->
            :ets.delete(s.idle, key)
            oldest_idle(s, client)
        end

      _ ->
        nil
    end
  end

  # The connection of `client` in `state` the longest.
  defp oldest(table, client, state) do
    table
    |> :ets.select([{{:"$1", client, state, :"$2"}, [], [{{:"$2", :"$1"}}]}])
    |> Enum.min(fn -> nil end)
    |> case do
      nil -> nil
      {_since, pid} -> pid
    end
  end

  # The oldest stream of the client with the most connections, if it holds more than `held` + 1.
  defp heaviest_stream(s, held) do
    case Enum.max_by(s.clients, fn {_c, e} -> e.count end, fn -> nil end) do
      {client, %{count: n}} when n > held + 1 -> oldest(s.table, client, :stream)
      _ -> nil
    end
  end

  defp shed(s, pid) do
    Process.exit(pid, :kill)

    case :ets.take(s.table, pid) do
      [{^pid, client, state, since}] ->
        if state == :idle, do: :ets.delete(s.idle, {since, pid})
        add(s, client, -1)

      [] ->
        s
    end
  end

  defp now, do: System.monotonic_time(:microsecond)
end
