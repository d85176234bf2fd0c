defmodule Vws.Ops.CrashLog do
  @moduledoc """
  Every crashed process is logged once, with its reason — state machines included (issue 30
  item 8). A Logger translator, added by `Vws.Application` at start.

  Why it is needed: Elixir 1.14's `Logger.Translator` turns a GenServer's termination report
  into the familiar "GenServer … terminating" line, but answers `:skip` for a `:gen_statem`'s
  (`%{label: {:gen_statem, :terminate}}`), and the other report of the same crash — proc_lib's
  crash report — is in the `[:otp, :sasl]` domain, which Logger drops unless
  `handle_sasl_reports` is on (and turning that on would log every GenServer crash twice, with
  every supervisor report besides). So a crashing SUN_COMM, DNC link, DDCMP or HPIB link wrote
  nothing at all. This translator writes the gen_statem's report as Logger writes a
  GenServer's: the process, its module, the reason (exception and stacktrace, or the exit
  reason), the event it was handling and, when the log level is debug, its state.

  It never raises (a translator that raises would cost the log its handler): anything it cannot
  read it leaves to the translators after it.

  A process killed from outside (`Process.exit(pid, :kill)`, an operator's `:erlang.exit/2`, the
  OOM-guard of a supervisor's `max_heap_size`) writes no report of its own: it has no chance to.
  The only trace is its supervisor's `child_terminated` report, again in the `[:otp, :sasl]`
  domain that Logger drops. `install/0` therefore also adds a `:logger` handler of its own that
  reads supervisor reports and writes one error line for a child that ended `:killed` — only that
  reason, since every other abnormal end was already reported by the process itself, and
  logging those too would say each crash twice — and only for a child its supervisor restarts
  (a link, a partition, a server): a temporary one (an HTTP connection the web server closes
  by killing its process to make room for a new client) is work given up on purpose, and under
  2,000 hostile sockets a line for each would be a flood of its own.
  """

  require Logger

  @handler :vws_killed_children

  @doc """
  Adds the translator and the killed-children handler. Idempotent: a second call (a test that
  restarts the application) replaces nothing and adds nothing twice.
  """
  @spec install() :: :ok
  def install do
    :ok = Logger.add_translator({__MODULE__, :translate})

    case :logger.add_handler(@handler, __MODULE__, %{level: :error}) do
      :ok -> :ok
      {:error, {:already_exist, @handler}} -> :ok
    end
  end

  @doc false
  # :logger handler callback: a supervisor's report of a child that was killed
  def log(%{msg: {:report, %{label: {:supervisor, :child_terminated}, report: report}}}, _config) do
    with :killed <- Keyword.get(report, :reason),
         offender when is_list(offender) <- Keyword.get(report, :offender),
         restart when restart in [:permanent, :transient] <- Keyword.get(offender, :restart_type) do
      Logger.error(
        [
          "process ",
          inspect(Keyword.get(offender, :pid)),
          " (child ",
          inspect(Keyword.get(offender, :id)),
          " of ",
          supervisor_name(Keyword.get(report, :supervisor)),
          ") was killed; it could write no report of its own"
        ],
        crash_reason: {:killed, []}
      )
    end

    :ok
  rescue
    _ -> :ok
  end

  def log(_event, _config), do: :ok

  # a supervisor as its report names it: {:local, name}, {:global, name}, {pid, module}
  defp supervisor_name({:local, name}), do: inspect(name)
  defp supervisor_name({:global, name}), do: inspect({:global, name})
  defp supervisor_name({:via, _, name}), do: inspect(name)
  defp supervisor_name({pid, module}) when is_pid(pid), do: [inspect(pid), " ", inspect(module)]
  defp supervisor_name(other), do: inspect(other)

  @doc false
  # Logger translator: {:ok, chardata, metadata} | :skip | :none
  def translate(min_level, _level, :report, {:logger, %{label: {:gen_statem, :terminate}} = r}) do
    gen_statem_terminate(min_level, r)
  rescue
    _ -> :none
  end

  def translate(_min_level, _level, _kind, _message), do: :none

  defp gen_statem_terminate(min_level, %{name: name, reason: {class, reason, stack}} = r) do
    opts = Application.get_env(:logger, :translator_inspect_opts, [])
    {crash_reason, formatted} = format_reason(class, reason, stack)

    module =
      case r do
        %{modules: [module | _]} -> [" (", inspect(module), ")"]
        _ -> []
      end

    event =
      case r do
        %{queue: [event | _]} -> ["\nLast event: ", inspect(event, opts)]
        _ -> []
      end

    state =
      if min_level == :debug and Map.has_key?(r, :state),
        do: ["\nState: ", inspect(r.state, opts)],
        else: []

    client =
      case r do
        %{client_info: {pid, :dead}} -> ["\nClient ", inspect(pid), " is dead"]
        %{client_info: {pid, _}} when is_pid(pid) -> ["\nClient ", inspect(pid), " is alive"]
        _ -> []
      end

    message = [
      [":gen_statem ", inspect(name), module, " terminating\n"],
      formatted,
      event,
      state,
      client
    ]

    metadata =
      [crash_reason: crash_reason] ++ if(is_atom(name), do: [registered_name: name], else: [])

    {:ok, message, metadata}
  end

  defp gen_statem_terminate(_min_level, _report), do: :none

  # as Logger does for a GenServer: an error is an exception with its stacktrace, an exit its term
  defp format_reason(:error, reason, stack) do
    exception = Exception.normalize(:error, reason, stack)
    {{exception, stack}, Exception.format(:error, exception, stack)}
  end

  defp format_reason(class, reason, stack),
    do: {{reason, stack}, Exception.format(class, reason, stack)}
end
