defmodule Vws.Test.RemoteHydraulic do
  @moduledoc """
  Runs on another node (a `:peer` in tests): a plant, DAQ #2 on it and the hydraulic controller,
  under a supervisor of their own that outlives the call that starts them.
  """

  @doc """
  Starts them; returns `%{endpoint, plant, name}` (`plant` a registered name, usable from the
  calling node through `:peer.call/4`). Options: `:time_scale` (1000), `:name`.
  """
  def start(opts \\ []) do
    name = Keyword.get(opts, :name, :remote)
    plant = {:via, Registry, {Vws.Registry, {name, :plant}}}
    daq2 = {:via, Registry, {Vws.Registry, {name, :daq2}}}

    children = [
      {Vws.Sim.Plant, name: plant, time_scale: Keyword.get(opts, :time_scale, 1000)},
      {Vws.Sim.DAQ, name: daq2, plant: plant, daq: :daq2},
      %{
        id: :controller,
        type: :supervisor,
        start:
          {__MODULE__, :start_controller,
           [[name: name, step_timeout_ms: 300, timeout_ms: 300], daq2]}
      }
    ]

    {:ok, sup} = Supervisor.start_link(children, strategy: :rest_for_one)
    Process.unlink(sup)
    :ok = Vws.Peers.HydraulicController.await_ready(name, 10_000)
    %{endpoint: Vws.Peers.HydraulicController.endpoint(name), plant: plant, name: name}
  end

  @doc false
  def start_controller(opts, daq2),
    do: Vws.Peers.HydraulicController.start_link([daq2: Vws.Sim.DAQ.endpoint(daq2)] ++ opts)
end
