defmodule Vws.Ops.Web.History do
  @moduledoc """
  The node's recent history for the dashboard: per workstation, a bounded ring (the last
  #{200} events) of what happened, each with the node's wall-clock time of the moment it was
  recorded — not the time a page saw it — so a page that is reloaded still shows it.

  What it records:

    * every command status change the mailbox writes (`Vws.CEC.Mailbox`'s change notices, which
      carry the system time of the write): `R 0007 EXECUTING ROBOT_PICK(…)`, `F 9001 DONE`, …;
    * every control action of the dashboard (`Vws.Ops.Web.Command`): sent, or refused and why;
    * every drip feed restarted at a line (issue 27; MONARCH's telemetry
      `[:vws, :monarch, :drip_restart]`, told before the first block is sent): the program, the
      version, the line and the preamble that restores the modal state — and the last one per
      workstation is kept whole for the dashboard's "Drip-feed restart" box (`restart/1`).

  One process per node (named `#{inspect(__MODULE__)}`, started with the first web server); it
  subscribes to the workstations it finds (looked for again every second). An event is
  `%{time: "2026-11-26T22:53:17.123Z", where: "ROBOT", text: "0007 DONE", severity: "ok"}`.
  """

  use GenServer

  @keep 200
  @look_every 1_000

  @doc "How many events are kept per workstation."
  def keep, do: @keep

  def child_spec(opts),
    do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}, restart: :permanent}

  @doc """
  Starts the node's history under the application's `Vws.WebSupervisor` unless it runs already:
  it outlives any one web server, so a server stopped (a test's) takes no history with it.
  """
  @spec ensure_started() :: :ok
  def ensure_started do
    case DynamicSupervisor.start_child(Vws.WebSupervisor, __MODULE__) do
      {:ok, _} -> :ok
      :ignore -> :ok
      {:error, {:already_started, _}} -> :ok
    end
  end

  @doc "Starts the node's history, unless it runs already (then `:ignore`)."
  def start_link(_opts \\ []) do
    case GenServer.start_link(__MODULE__, nil, name: __MODULE__) do
      {:error, {:already_started, _}} -> :ignore
      other -> other
    end
  end

  @doc "The recent events of a workstation, oldest first (`[]` when the history does not run)."
  @spec recent(term) :: [map]
  def recent(ws) do
    case :ets.whereis(__MODULE__) do
      :undefined ->
        []

      _ ->
        :ets.select(__MODULE__, [{{{ws, :_}, :"$1"}, [], [:"$1"]}])
    end
  rescue
    ArgumentError -> []
  end

  @doc "Records an event of a workstation now (the node's time)."
  @spec record(term, String.t(), String.t(), String.t()) :: :ok
  def record(ws, where, text, severity) do
    if pid = Process.whereis(__MODULE__) do
      send(pid, {:record, ws, System.system_time(:microsecond), where, text, severity})
    end

    :ok
  end

  @doc """
  The last drip-feed restart told on this node for `ws`, nil if none: `%{time, program, version,
  line, preamble}` — `preamble` the lines sent before line `line` (`Vws.Codecs.NCModal`).
  """
  @spec restart(term) :: map | nil
  def restart(ws) do
    case :ets.whereis(__MODULE__) do
      :undefined ->
        nil

      _ ->
        case :ets.lookup(__MODULE__, {:restart, ws, :last}) do
          [{_, shown}] -> shown
          [] -> nil
        end
    end
  rescue
    ArgumentError -> nil
  end

  @doc false
  # MONARCH's [:vws, :monarch, :drip_restart], in the process that is about to send the program:
  # handed to the history at once, with the moment it was told.
  def drip_restart(_event, %{line: line}, meta, _config) do
    if pid = Process.whereis(__MODULE__) do
      send(pid, {:drip_restart, meta.workstation, System.system_time(:microsecond), meta, line})
    end

    :ok
  end

  @doc "Makes sure the workstation's events are recorded from now on (they are within a second anyway)."
  @spec watch(term) :: :ok
  def watch(ws) do
    if Process.whereis(__MODULE__), do: GenServer.call(__MODULE__, {:watch, ws}, 5_000)
    :ok
  catch
    :exit, _ -> :ok
  end

  @impl true
  def init(nil) do
    :ets.new(__MODULE__, [:ordered_set, :protected, :named_table, read_concurrency: true])
    # told as soon as a workstation joins the cell, so its first commands are not missed (a
    # look every second finds any the cell did not tell of)
    _ = :pg.monitor_scope(Vws.CEC.Cell.scope())
    send(self(), :look)
    # the handler of a history started before this one is replaced (its process is gone)
    Vws.Telemetry.detach({__MODULE__, :drip_restart})

    :ok =
      Vws.Telemetry.attach(
        {__MODULE__, :drip_restart},
        [:vws, :monarch, :drip_restart],
        &__MODULE__.drip_restart/4,
        nil
      )

    {:ok, %{watched: MapSet.new(), seq: 0, counts: %{}}}
  end

  @impl true
  def handle_call({:watch, ws}, _from, s) do
    if MapSet.member?(s.watched, ws) do
      {:reply, :ok, s}
    else
      :ok = Vws.CEC.Events.subscribe(ws, :mailbox)
      {:reply, :ok, %{s | watched: MapSet.put(s.watched, ws)}}
    end
  end

  @impl true
  def handle_info(:look, s) do
    new =
      for ws <- Vws.CEC.Workstation.list(), not MapSet.member?(s.watched, ws) do
        :ok = Vws.CEC.Events.subscribe(ws, :mailbox)
        ws
      end

    Process.send_after(self(), :look, @look_every)
    {:noreply, %{s | watched: MapSet.union(s.watched, MapSet.new(new))}}
  end

  def handle_info({:vws_event, ws, :mailbox, {{:command, p, n, status, text}, at}}, s) do
    word = Vws.CEC.Mailbox.status_word(status)
    shown = Enum.join(Enum.reject([Vws.Codecs.WC.Command.pad4(n), word, text], &is_nil/1), " ")

    {:noreply, put(s, ws, at, String.upcase(to_string(p)), shown, Vws.Ops.Web.Severity.of(word))}
  end

  def handle_info({:record, ws, at, where, text, severity}, s),
    do: {:noreply, put(s, ws, at, where, text, severity)}

  def handle_info({:drip_restart, ws, at, meta, line}, s) do
    preamble = Enum.map(meta.preamble, &to_string/1)
    program = to_string(meta.program)

    text =
      "DRIP_FEED of #{program} version #{meta.version} restarts at line #{line}, " <>
        "restored preamble: #{Enum.join(preamble, " / ")}"

    s = put(s, ws, at, "MONARCH", text, "ok")

    shown = %{
      time: time(at),
      program: program,
      version: meta.version,
      line: line,
      preamble: preamble
    }

    :ets.insert(__MODULE__, {{:restart, ws, :last}, shown})
    {:noreply, s}
  end

  def handle_info({_ref, :join, {:workstation, ws}, _pids}, s) do
    if MapSet.member?(s.watched, ws) do
      {:noreply, s}
    else
      :ok = Vws.CEC.Events.subscribe(ws, :mailbox)
      {:noreply, %{s | watched: MapSet.put(s.watched, ws)}}
    end
  end

  def handle_info(_other, s), do: {:noreply, s}

  defp put(s, ws, at_us, where, text, severity) do
    seq = s.seq + 1

    :ets.insert(
      __MODULE__,
      {{ws, seq}, %{time: time(at_us), where: where, text: text, severity: severity}}
    )

    count = Map.get(s.counts, ws, 0) + 1

    count =
      if count > @keep do
        oldest = :ets.next(__MODULE__, {ws, 0})
        :ets.delete(__MODULE__, oldest)
        count - 1
      else
        count
      end

    %{s | seq: seq, counts: Map.put(s.counts, ws, count)}
  end

  defp time(at_us) do
    at_us
    |> DateTime.from_unix!(:microsecond)
    |> DateTime.truncate(:millisecond)
    |> DateTime.to_iso8601()
  end
end
