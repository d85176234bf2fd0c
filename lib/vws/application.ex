defmodule Vws.Application do
  @moduledoc false
  use Application

  require Logger

  @impl true
  def start(_type, _args) do
    # SIGTERM and SIGQUIT stop the node in order (Vws.Ops.Signals)
    :ok = Vws.Ops.Signals.install()
    # the log in rotating files too, where configured (VWS_LOG_DIR)
    :ok = Vws.Ops.LogFile.start_configured()
    # a crashing :gen_statem (SUN_COMM, the links) is logged as a crashing GenServer is. Added
    # once (add_translator replaces an equal one) and never removed: removing it in stop/1 waits
    # on the application controller, which is busy stopping this application (a deadlock)
    :ok = Logger.add_translator({Vws.Ops.CrashLog, :translate})

    children =
      [
        {Registry, keys: :unique, name: Vws.Registry},
        {Registry,
         keys: :duplicate, name: Vws.CEC.Events, partitions: System.schedulers_online()},
        # the :pg scope every workstation joins: the cell across connected nodes (Vws.CEC.Cell)
        Vws.CEC.Cell,
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
  defp configured_workstation do
    case Application.get_env(:vws, :workstation) do
      nil ->
        []

      opts ->
        opts = Enum.reject(opts, fn {_k, v} -> v == nil end)

        [
          Supervisor.child_spec(
            {Task, fn -> {:ok, _} = start_configured(opts) end},
            id: :configured_workstation,
            restart: :temporary
          )
        ]
    end
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
      nil -> []
      opts -> [Supervisor.child_spec({Vws.Ops.Web, opts}, id: :configured_http)]
    end
  end
end
