defmodule Vws.Application do
  @moduledoc false
  use Application

  require Logger

  @impl true
  def start(_type, _args) do
    # SIGTERM and SIGQUIT stop the node in order (Vws.Ops.Signals)
    :ok = Vws.Ops.Signals.install()
    # a release started in a terminal (`bin/vws start`): one Ctrl-C stops it in order, as in
    # `mix vws.serve` (the mix tasks ask for it themselves)
    if System.get_env("RELEASE_COMMAND") in ["start", "start_iex"],
      do: Vws.Ops.Signals.ctrl_c_stops()

    # the log in rotating files too, where configured (VWS_LOG_DIR)
    :ok = Vws.Ops.LogFile.start_configured()
    # a crashing :gen_statem (SUN_COMM, the links) is logged as a crashing GenServer is, and a
    # killed child once by its supervisor's report. Added once (add_translator replaces an equal
    # one) and never removed: removing it in stop/1 waits on the application controller, which
    # is busy stopping this application (a deadlock)
    :ok = Vws.Ops.CrashLog.install()

    children =
      [
        {Registry, keys: :unique, name: Vws.Registry},
        # one partition: a duplicate registry is partitioned by subscriber, so every CAUSE EVENT
        # (two per VWS_STATUS poll, two per WC string) would look in every partition — 32
        # reductions with 2 schedulers, 86 with 8, against 15; subscribing is rare
        {Registry, keys: :duplicate, name: Vws.CEC.Events, partitions: 1},
        # the :pg scope every workstation joins: the cell across connected nodes (Vws.CEC.Cell)
        Vws.CEC.Cell,
        # is the node doing its job: /health, bin/vws health (the workstations it must run)
        Vws.Ops.Health,
        # VWS_STATUS's load shedding for every workstation of the node
        Vws.Partitions.VwsStatus.Shedding,
        # equipment started beside the workstations on this node — a simulated floor
        # (`mix vws.serve`, `mix vws.demo`), a hydraulic controller of its own: it stops after
        # them, and before the registry its processes are named in
        {DynamicSupervisor, name: Vws.EquipmentSupervisor, strategy: :one_for_one},
        {DynamicSupervisor, name: Vws.WorkstationSupervisor, strategy: :one_for_one},
        {DynamicSupervisor, name: Vws.WebSupervisor, strategy: :one_for_one}
      ] ++ configured_workstation() ++ configured_http()

    Supervisor.start_link(children, strategy: :one_for_one, name: Vws.Supervisor)
  end

  @impl true
  def stop(_state) do
    :ok = Vws.Ops.LogFile.stop()
    Vws.Ops.Signals.uninstall()
  end

  # The workstation of config/runtime.exs (a deployment), started under the workstation supervisor.
  # A node that cannot start it does not run on without it (hosting nothing, its exit status
  # never changing): it says why in one line and exits with status 1 (systemd's
  # Restart=on-failure, an operator at the terminal) — no crash dump, no stack trace.
  defp configured_workstation do
    case Application.get_env(:vws, :workstation) do
      nil ->
        []

      opts ->
        opts = Enum.reject(opts, fn {_k, v} -> v == nil end)

        [
          Supervisor.child_spec(
            {Task,
             fn ->
               case start_checked(opts) do
                 {:ok, _} -> :ok
                 {:error, line} -> fatal("workstation #{opts[:id]} cannot start: #{line}")
               end
             end},
            id: :configured_workstation,
            restart: :temporary
          )
        ]
    end
  end

  @doc false
  # The configured workstation started, its WC port open and the node's health expecting it —
  # or `{:error, line}`: why not, in words (Vws.Ops.StartError).
  def start_checked(opts) do
    id = Keyword.fetch!(opts, :id)

    with :ok <- check_endpoint(opts[:wc]),
         :ok <- check_policy(opts[:wc], get_in(opts, [:sun_comm, :allow])),
         :ok <- check_wc_port(opts[:wc]),
         {:ok, pid} <- start_configured(opts),
         :ok <- Vws.Ops.Health.expect(id),
         :ok <- await_wc(id, opts[:wc], 10_000) do
      {:ok, pid}
    else
      {:error, reason} -> {:error, Vws.Ops.StartError.describe(reason)}
    end
  rescue
    e -> {:error, Exception.message(e)}
  catch
    :exit, reason -> {:error, Vws.Ops.StartError.describe(reason)}
  end

  # VWS_WC that cannot be read, said as the variable it came from
  defp check_endpoint(wc) do
    case Vws.Links.Endpoint.parse(wc) do
      {:ok, _} -> :ok
      {:error, e} -> {:error, "VWS_WC: " <> Exception.message(e)}
    end
  end

  # Who may connect (VWS_WC_ALLOW), judged before SUN_COMM starts: a listen address that is not
  # loopback without an allow-list is one line here, not a SUN_COMM that fails to start
  defp check_policy(wc, allow) do
    with {:ok, allow} <- prefix(Vws.Links.Transport.Policy.parse_allow(allow), "VWS_WC_ALLOW: ") do
      Vws.Links.Transport.Policy.check_listen(wc, allow)
    end
  end

  defp prefix({:error, message}, text) when is_binary(message), do: {:error, text <> message}
  defp prefix(other, _text), do: other

  @doc false
  # A TCP WC port that cannot be listened on (in use, not an address of this host, below 1024),
  # found before anything starts: `{:error, {:cannot_listen, wc, reason}}`. Anything else
  # (a tty, an endpoint that cannot be read) is SUN_COMM's to judge.
  def check_wc_port("tcp:" <> _ = wc) do
    case Vws.Links.Transport.listen(wc) do
      {:ok, listener} ->
        Vws.Links.Transport.close_listener(listener)
        :ok

      {:error, %Vws.Links.Transport.Error{} = e} ->
        {:error, {:cannot_listen, wc, e}}

      {:error, _endpoint_error} ->
        :ok
    end
  end

  def check_wc_port(_wc), do: :ok

  @doc false
  # Waits (at most `timeout` ms) until workstation `id`'s SUN_COMM listens on a TCP WC endpoint:
  # `:ok`, or `{:error, reason}` if it stopped first (its port taken meanwhile). A tty is not waited for: SUN_COMM
  # opens it again every second, and /health says while it cannot.
  def await_wc(id, "tcp:" <> _, timeout) do
    case Vws.CEC.Workstation.whereis(id, :sun_comm) do
      nil ->
        {:error, "its SUN_COMM did not start"}

      pid ->
        ref = Process.monitor(pid)
        :ok = Vws.CEC.Events.subscribe(id, :wc_listening)

        listening =
          try do
            Vws.CEC.SunComm.listening(id)
          catch
            :exit, _ -> nil
          end

        result =
          if listening do
            :ok
          else
            receive do
              {:vws_event, ^id, :wc_listening, _endpoint} -> :ok
              {:DOWN, ^ref, :process, _, reason} -> {:error, reason}
            after
              # slow, not failed (a loaded machine): /health tells if it never opens
              timeout -> :ok
            end
          end

        Vws.CEC.Events.unsubscribe(id, :wc_listening)
        Process.demonitor(ref, [:flush])
        result
    end
  end

  def await_wc(_id, _wc, _timeout), do: :ok

  @doc false
  # The configured dashboard, or — its port in use, its address not this host's — one line and
  # status 1, as for the workstation (a failed child here took the node down with a crash dump).
  def start_http(opts) do
    case Vws.Ops.Web.start_link(opts) do
      {:ok, pid} ->
        {:ok, pid}

      {:error, reason} ->
        fatal(
          "the dashboard cannot start: #{Vws.Ops.StartError.describe(reason)} (VWS_HTTP_PORT)"
        )
    end
  end

  @doc false
  # One line on the console (and in the log file), then exit status 1: no crash dump, no stack.
  def fatal(line) do
    Logger.error(line)
    Logger.flush()

    try do
      :logger_std_h.filesync(:vws_file)
    catch
      _, _ -> :ok
    end

    System.halt(1)
  end

  @doc false
  # The configured workstation. `devices: [daq2: endpoint]` (VWS_DAQ2) runs the hydraulic
  # controller in this node, on DAQ #2, under the equipment supervisor, and gives the
  # workstation its endpoint — unless the workstation has one elsewhere (VWS_HYDRAULIC).
  def start_configured(opts) do
    {daq2, devices} = Keyword.pop(Keyword.get(opts, :devices, []), :daq2)

    devices =
      cond do
        daq2 == nil ->
          devices

        Keyword.has_key?(devices, :hydraulic) ->
          Logger.warning("VWS_DAQ2 not used: the hydraulic controller is at VWS_HYDRAULIC")
          devices

        true ->
          name = {:configured, Keyword.fetch!(opts, :id)}

          {:ok, _} =
            DynamicSupervisor.start_child(
              Vws.EquipmentSupervisor,
              {Vws.Peers.HydraulicController, name: name, daq2: daq2}
            )

          :ok = Vws.Peers.HydraulicController.await_ready(name, 30_000)
          devices ++ [hydraulic: Vws.Peers.HydraulicController.endpoint(name)]
      end

    Vws.CEC.Workstation.start(Keyword.put(opts, :devices, devices))
  end

  # The dashboard and MTConnect agent of config/runtime.exs (`config :vws, :http, port: …`).
  # Nothing is configured in dev and test: there the mix tasks and the tests start what they need.
  defp configured_http do
    case Application.get_env(:vws, :http) do
      nil ->
        []

      opts ->
        spec = Supervisor.child_spec({Vws.Ops.Web, opts}, id: :configured_http)
        [%{spec | start: {__MODULE__, :start_http, [opts]}}]
    end
  end
end
