defmodule Vws.CEC.Partition do
  @moduledoc """
  The GenServer that runs each of the six command partitions (ROBOT, MONARCH, GRIPPER, FIXTURE,
  VACUUM, HYDRAULIC) over its command set, a module implementing `Vws.CEC.Partition.CommandSet`.

  It is the seed's partition loop (§2.3, Fig. 4): wait in ON EVENT for the partition's event, read
  CMD_IN, set the command status `EXECUTING`, run the command, then set `DONE` or
  `ERROR <reason>`.

  The command set's `execute/2` runs in a process of its own, linked to the partition, so the
  partition stays responsive (status, inspection) while a robot moves; if it raises or exits the
  command ends `ERROR` with the reason. If the partition itself dies, the linked command process
  dies with it, and the restarted partition ends the command it finds in flight with
  `ERROR INTERRUPTED BY PARTITION RESTART` — it never runs it again by itself.

  ## Interlocks

  Between the grammar and `execute/2`, every command passes the one interlock table,
  `Vws.CEC.Interlock.Rules`: the work volumes it needs are taken first (a refusal ends it
  `ERROR INTERLOCK …` before the device acts) and kept or given back as the table says once it
  has ended. The command set takes part through its optional callbacks `volumes/2`,
  `conditions/2` and `missing_link/2`.

  ## After a restart of the workstation

  A command the journal found `EXECUTING` when the workstation went down answers
  `ERROR INTERRUPTED BY RESTART` and is never run again. What the command set may do instead is
  its safe clean-up, the optional callback `interrupted/2`. The restarted partition runs it in a
  process of its own, trying again every `:cleanup_retry_ms` (250) until `:cleanup_timeout_ms`
  (60 000) while its device is not reachable yet, and reports it as
  `[:vws, :partition, :cleaned_up]` (`status` `:ok` or `{:error, reason}`).

  A partition started without a link to its device (`link: nil`) answers every valid command
  `ERROR NO LINK TO <device>`; an invalid one gets `ERROR UNKNOWN COMMAND <text>` either way.
  """
  use GenServer
  require Logger

  alias Vws.CEC.{Events, Mailbox}
  alias Vws.CEC.Interlock.Rules
  alias Vws.Codecs.WC.Words

  @doc false
  def child_spec(opts) do
    %{
      id: Keyword.fetch!(opts, :partition),
      start: {__MODULE__, :start_link, [opts]},
      shutdown: 5_000
    }
  end

  @doc """
  Starts a partition. Options: `:workstation`, `:partition` (its set), `:module` (its command set,
  `Vws.CEC.Partition.CommandSet`), `:link` (whatever the module needs to reach its device, `nil` when not configured) and
  `:options` (passed to the module in `ctx.options`), `:interlocks` (`:on`; `:off` only for a
  stand-in module whose commands are not a seed set's, see `Vws.CEC.Workstation`).
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    partition = Keyword.fetch!(opts, :partition)
    GenServer.start_link(__MODULE__, opts, name: via(ws, partition))
  end

  @doc "The registered name of a workstation's partition."
  def via(ws, partition), do: Vws.Names.via(ws, partition)

  @doc "The pid of a workstation's partition, or nil."
  @spec whereis(term, Mailbox.partition()) :: pid | nil
  def whereis(ws, partition), do: Vws.Names.whereis(ws, partition)

  @doc """
  What a partition is doing: `%{partition, current: nil | %{number, text, running_ms}, done,
  errors, restarts}`.
  """
  @spec info(term, Mailbox.partition()) :: map
  def info(ws, partition), do: GenServer.call(via(ws, partition), :info)

  @doc """
  Hands command `number` to a workstation's partition: CMD_IN written and the command in flight
  (`Vws.CEC.Mailbox.dispatch/4`, durable first), `[:vws, :partition, :command_dispatched]`, then
  the partition's event, on which it runs it. `{:busy, previous}` while its previous command is
  in flight and `{:error, words}` when the dispatch could not be made durable: then nothing runs.
  """
  @spec dispatch(term, Mailbox.partition(), 0..9999, String.t()) ::
          :ok | {:busy, 0..9999} | {:error, String.t()}
  def dispatch(ws, partition, number, text) do
    with :ok <- Mailbox.dispatch(ws, partition, number, text) do
      # before the event: what the command does comes after its dispatch, in every record
      Vws.Telemetry.execute([:vws, :partition, :command_dispatched], %{count: 1}, %{
        workstation: ws,
        partition: partition,
        command: number,
        text: text
      })

      :ok = Events.cause(ws, partition, number)
    end
  end

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    ws = Keyword.fetch!(opts, :workstation)
    partition = Keyword.fetch!(opts, :partition)
    Logger.metadata(workstation: ws, partition: partition)

    Events.create(ws, partition)
    :ok = Events.subscribe(ws, partition)

    restarts =
      :ets.update_counter(Mailbox.table(ws), {:starts, partition}, 1, {{:starts, partition}, 0}) -
        1

    # Subscribed first, then the in-flight check: a command dispatched while we were down is
    # ended here; one dispatched from now on reaches us as an event.
    case Mailbox.in_flight(ws, partition) do
      nil ->
        :ok

      number ->
        Logger.warning(
          "command #{number} was in flight when the partition restarted: ending it ERROR"
        )

        finish(ws, partition, number, {:error, "INTERRUPTED BY PARTITION RESTART"}, 0)
    end

    module = Keyword.fetch!(opts, :module)

    case Vws.CEC.Journal.take_interrupted(ws, partition) do
      nil ->
        :ok

      {number, text} ->
        clean_up(module, %{
          workstation: ws,
          partition: partition,
          number: number,
          text: text,
          link: Keyword.get(opts, :link),
          options: Keyword.get(opts, :options, [])
        })
    end

    {:ok,
     %{
       workstation: ws,
       partition: partition,
       module: Keyword.fetch!(opts, :module),
       link: Keyword.get(opts, :link),
       options: Keyword.get(opts, :options, []),
       interlocks: Keyword.get(opts, :interlocks, :on),
       current: nil,
       done: 0,
       errors: 0,
       restarts: restarts
     }}
  end

  @impl true
  def handle_info(
        {:vws_event, ws, partition, number},
        %{workstation: ws, partition: partition} = s
      )
      when is_integer(number) do
    case {s.current, Mailbox.in_flight(ws, partition), Mailbox.cmd_in(ws, partition)} do
      {nil, ^number, {^number, text}} ->
        {:noreply, start_command(s, number, text)}

      other ->
        Logger.warning("event for command #{number} ignored: #{inspect(other)}")
        {:noreply, s}
    end
  end

  def handle_info({:command_result, pid, result}, %{current: %{pid: pid}} = s) do
    {:noreply, end_command(s, result)}
  end

  def handle_info({:EXIT, pid, reason}, %{current: %{pid: pid}} = s) when reason != :normal do
    {:noreply, end_command(s, {:error, "CRASHED #{exit_reason(reason)}"})}
  end

  def handle_info({:EXIT, _pid, :normal}, s), do: {:noreply, s}

  def handle_info({:EXIT, _pid, reason}, s) do
    # our supervisor (or a linked link process) is going down
    {:stop, reason, s}
  end

  def handle_info(msg, s) do
    Logger.warning("unexpected message #{inspect(msg, limit: 10)}")
    {:noreply, s}
  end

  @impl true
  def handle_call(:info, _from, s) do
    current =
      s.current &&
        %{
          number: s.current.number,
          text: s.current.text,
          running_ms:
            System.convert_time_unit(
              System.monotonic_time() - s.current.started,
              :native,
              :millisecond
            )
        }

    {:reply,
     %{
       partition: s.partition,
       pid: self(),
       current: current,
       done: s.done,
       errors: s.errors,
       restarts: s.restarts,
       link: s.link
     }, s}
  end

  @impl true
  def terminate(_reason, %{current: %{pid: pid}}), do: Process.exit(pid, :kill)
  def terminate(_reason, _s), do: :ok

  defp start_command(s, number, text) do
    parent = self()

    ctx = %{
      workstation: s.workstation,
      partition: s.partition,
      number: number,
      text: text,
      link: s.link,
      options: s.options,
      interlocks: s.interlocks
    }

    module = s.module

    pid =
      spawn_link(fn ->
        Logger.metadata(workstation: ctx.workstation, partition: ctx.partition, command: number)
        send(parent, {:command_result, self(), run(module, ctx)})
      end)

    %{s | current: %{pid: pid, number: number, text: text, started: System.monotonic_time()}}
  end

  defp end_command(s, result) do
    %{number: number, started: started} = s.current
    status = if result == :done, do: :done, else: result
    finish(s.workstation, s.partition, number, status, System.monotonic_time() - started)

    if status == :done,
      do: %{s | current: nil, done: s.done + 1},
      else: %{s | current: nil, errors: s.errors + 1}
  end

  @doc false
  # Runs one command: grammar, link, then the module's execute/2, inside a telemetry span.
  def run(module, ctx) do
    meta = %{
      workstation: ctx.workstation,
      partition: ctx.partition,
      command: ctx.number,
      text: ctx.text
    }

    Vws.Telemetry.span([:vws, :partition, :command], meta, fn ->
      result =
        case module.parse(ctx.text) do
          {:error, :unknown} -> {:error, "UNKNOWN COMMAND " <> ctx.text}
          {:error, reason} -> {:error, reason}
          {:ok, _command} when ctx.link == nil -> {:error, "NO LINK TO " <> module.device()}
          {:ok, command} -> guarded(module, command, ctx)
        end

      {result, Map.put(meta, :result, result)}
    end)
  end

  # Every command passes the one interlock table (`Vws.CEC.Interlock.Rules`): what it needs is
  # taken before the device acts, and kept or given back as the table says once it has ended.
  defp guarded(module, command, ctx) do
    missing =
      if function_exported?(module, :missing_link, 2), do: module.missing_link(command, ctx)

    cond do
      missing ->
        {:error, "NO LINK TO " <> missing}

      Map.get(ctx, :interlocks, :on) == :off ->
        normalise(module.execute(command, ctx))

      true ->
        with {:ok, taken} <- Rules.acquire(module, command, ctx) do
          result = normalise(module.execute(command, ctx))
          :ok = Rules.finish(command, taken, ctx, result)
          result
        end
    end
  end

  # The safe clean-up of a command the workstation's restart interrupted (see the moduledoc),
  # in a process of its own: the device may not be reachable for a while yet.
  defp clean_up(module, ctx) do
    with {:module, _} <- Code.ensure_loaded(module),
         true <- function_exported?(module, :interrupted, 2),
         {:ok, command} <- interrupted_command(module, ctx.text) do
      retry = Keyword.get(ctx.options, :cleanup_retry_ms, 250)

      deadline =
        System.monotonic_time(:millisecond) +
          Keyword.get(ctx.options, :cleanup_timeout_ms, 60_000)

      Task.start(fn ->
        Logger.metadata(workstation: ctx.workstation, partition: ctx.partition)
        status = clean_up_until(module, command, ctx, retry, deadline)

        what = what_was_interrupted(ctx)

        case status do
          :ok ->
            Logger.warning("#{what}: safe state restored")

          {:error, why} ->
            Logger.error("#{what}: safe state NOT restored (#{why})")
        end

        Vws.Telemetry.execute([:vws, :partition, :cleaned_up], %{count: 1}, %{
          workstation: ctx.workstation,
          partition: ctx.partition,
          command: ctx.number,
          text: ctx.text,
          status: status
        })
      end)
    else
      _ -> :ok
    end
  end

  # `:unknown`: the status was lost with a damaged journal, so whatever may have been under way
  # is cleaned up as an interrupted command would be (the callback's `:unknown` clause)
  defp interrupted_command(_module, :unknown), do: {:ok, :unknown}
  defp interrupted_command(module, text), do: module.parse(text || "")

  defp what_was_interrupted(%{text: :unknown}),
    do: "status unknown after the damaged journal (a command may have been under way)"

  defp what_was_interrupted(ctx),
    do: "command #{ctx.number} #{ctx.text} interrupted by the restart"

  defp clean_up_until(module, command, ctx, retry, deadline) do
    case safe(fn -> module.interrupted(command, ctx) end) do
      :ok ->
        :ok

      {:error, why} ->
        if System.monotonic_time(:millisecond) >= deadline do
          {:error, why}
        else
          Process.sleep(retry)
          clean_up_until(module, command, ctx, retry, deadline)
        end
    end
  end

  defp safe(fun) do
    case fun.() do
      :ok -> :ok
      {:error, why} when is_binary(why) -> {:error, Words.of(why)}
      other -> {:error, bad_result(other)}
    end
  rescue
    e -> {:error, Words.of(e)}
  catch
    kind, reason ->
      Logger.error("clean-up #{kind}: #{inspect(reason, limit: 20)}")
      {:error, Words.of(kind)}
  end

  # What a module returns is what the WC reads after ERROR: words and numbers, never a term
  # (Vws.Codecs.WC.Words); an unexpected result is logged whole and shown in words.
  defp normalise(:done), do: :done

  defp normalise({:error, reason}) when is_binary(reason) do
    if reason != "" and Words.text?(reason),
      do: {:error, reason},
      else: {:error, Words.of(reason)}
  end

  defp normalise(other), do: {:error, bad_result(other)}

  defp bad_result(other) do
    Logger.error(
      "a command ended with an unexpected result: #{inspect(other, limit: 8, printable_limit: 80)}"
    )

    "BAD RESULT " <> Words.of(other)
  end

  defp finish(ws, partition, number, status, duration) do
    Mailbox.finish(ws, partition, number, status)

    Vws.Telemetry.execute([:vws, :partition, :command_finished], %{duration: duration}, %{
      workstation: ws,
      partition: partition,
      command: number,
      status: status
    })
  end

  defp exit_reason({%{__exception__: true} = e, _stack}), do: Words.of(e)
  defp exit_reason(reason), do: Words.of(reason)
end
