defmodule Vws.Sim.Floor do
  @moduledoc """
  The simulated shop floor of one workstation: the plant (`Vws.Sim.Plant`), the two
  data-acquisition units on it (`Vws.Sim.DAQ`, each listening on its own endpoint) and,
  optionally, the hydraulic controller (`Vws.HydraulicController`) on DAQ #2.

  ```
  Vws.Sim.Floor (rest_for_one)
  ├── Vws.Sim.Plant        {ws, :sim_plant} in Vws.Registry — other simulators find it with plant/1
  ├── Vws.Sim.DAQ (DAQ #1) {ws, :sim_daq1}  — on :daq1 (default tcp://127.0.0.1:0); `daq1: false`: none
  ├── Vws.Sim.DAQ (DAQ #2) {ws, :sim_daq2}  — the pallet's channels, on :daq2 (default tcp://127.0.0.1:0)
  └── Vws.HydraulicController  named {:sim_floor, ws}, on DAQ #2 — only with `hydraulic: true`
  ```

  The hydraulic controller is not a simulator — it is the controller itself — but on the
  simulated floor it has nowhere else to run; it comes after DAQ #2, which it needs.
  `mix vws.serve` and `Vws.Demo` start the floor before the workstation and give the workstation
  `devices: [daq1: Vws.Sim.Floor.daq1_endpoint(ws), hydraulic: Vws.Sim.Floor.hydraulic_endpoint(ws)]`;
  pointing `daq1` and `hydraulic` at real equipment instead needs no floor at all.

      iex> {:ok, _floor} = Vws.Sim.Floor.start_link(workstation: "floor-doc", time_scale: 100)
      iex> Vws.Sim.Floor.daq1_endpoint("floor-doc") =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
      iex> Vws.Sim.Floor.daq2_endpoint("floor-doc") =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
      iex> Vws.Sim.Plant.snapshot(Vws.Sim.Floor.plant("floor-doc")).vise.jaw_mm
      150.0
  """
  use Supervisor

  alias Vws.HydraulicController
  alias Vws.Sim.{DAQ, Plant}

  @doc """
  Starts the floor of workstation `:workstation`. Options: `:time_scale` (default 1.0), `:seed`,
  `:plant` (more `Vws.Sim.Plant` options, e.g. `config:`), `:daq1` (the endpoint DAQ #1 listens
  on, default `"tcp://127.0.0.1:0"`; `false` for no DAQ #1), `:daq2` (the same for DAQ #2),
  `:hydraulic` (`true`, or `Vws.HydraulicController.start_link/1` options, to run the hydraulic
  controller on DAQ #2; default `false`).
  """
  @spec start_link(keyword) :: Supervisor.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    Supervisor.start_link(__MODULE__, opts, name: name(ws, :sim_floor))
  end

  @doc false
  def child_spec(opts) do
    %{
      id: {__MODULE__, Keyword.fetch!(opts, :workstation)},
      start: {__MODULE__, :start_link, [opts]},
      type: :supervisor
    }
  end

  @doc "The plant of a workstation's floor (a registered name), for the other simulators."
  @spec plant(term) :: GenServer.name()
  def plant(ws), do: name(ws, :sim_plant)

  @doc "The DAQ #1 simulator of a workstation's floor (a registered name)."
  @spec daq1(term) :: GenServer.name()
  def daq1(ws), do: name(ws, :sim_daq1)

  @doc "Where the DAQ #1 simulator listens, as an endpoint string."
  @spec daq1_endpoint(term) :: String.t()
  def daq1_endpoint(ws), do: DAQ.endpoint(daq1(ws))

  @doc "The DAQ #2 simulator of a workstation's floor (a registered name)."
  @spec daq2(term) :: GenServer.name()
  def daq2(ws), do: name(ws, :sim_daq2)

  @doc "Where the DAQ #2 simulator listens, as an endpoint string."
  @spec daq2_endpoint(term) :: String.t()
  def daq2_endpoint(ws), do: DAQ.endpoint(daq2(ws))

  @doc "The name of the floor's hydraulic controller (for `Vws.HydraulicController` calls)."
  @spec hydraulic_controller(term) :: term
  def hydraulic_controller(ws), do: {:sim_floor, ws}

  @doc "Where the floor's hydraulic controller is reached by the CEC, as an endpoint string."
  @spec hydraulic_endpoint(term) :: String.t()
  def hydraulic_endpoint(ws), do: HydraulicController.endpoint(hydraulic_controller(ws))

  @doc """
  For `Vws.Demo`'s shop floor: starts the floor with its hydraulic controller (linked to the
  caller) with the demo's `:workstation` and `:time_scale`, and returns the workstation links
  and partition options that reach it (`Vws.Partitions.VwsStatus.wiring/3` for DAQ #1,
  `Vws.Partitions.Hydraulic.wiring/3` for the hydraulic controller).
  """
  @spec shop_floor(keyword) ::
          {:ok, %{name: String.t(), links: [Supervisor.child_spec()], partitions: keyword}}
          | {:error, term}
  def shop_floor(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    floor_opts = Keyword.take(opts, [:workstation, :time_scale, :seed]) ++ [hydraulic: true]

    with {:ok, _pid} <- start_link(floor_opts),
         :ok <- HydraulicController.await_ready(hydraulic_controller(ws), 10_000) do
      daq1 = Vws.Partitions.VwsStatus.wiring(ws, daq1_endpoint(ws))
      hydraulic = Vws.Partitions.Hydraulic.wiring(ws, hydraulic_endpoint(ws))

      {:ok,
       %{
         name: "plant + DAQ #1 + DAQ #2 + hydraulic controller",
         links: daq1.links ++ hydraulic.links,
         partitions: daq1.partitions ++ hydraulic.partitions
       }}
    else
      :timeout -> {:error, :hydraulic_controller_not_ready}
      {:error, _} = error -> error
    end
  end

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    plant_opts =
      [name: plant(ws), time_scale: Keyword.get(opts, :time_scale, 1.0)] ++
        Keyword.take(opts, [:seed]) ++ Keyword.get(opts, :plant, [])

    daqs =
      for daq <- [:daq1, :daq2], Keyword.get(opts, daq) != false do
        endpoint = Keyword.get(opts, daq, "tcp://127.0.0.1:0")
        {DAQ, plant: plant(ws), name: name(ws, :"sim_#{daq}"), daq: daq, endpoint: endpoint}
      end

    hydraulic =
      case Keyword.get(opts, :hydraulic, false) do
        false ->
          []

        hopts ->
          hopts = if hopts == true, do: [], else: hopts
          daq2 = daq2(ws)

          [
            %{
              id: HydraulicController,
              type: :supervisor,
              # DAQ #2 listens before the controller starts: its endpoint is known by then
              start:
                {__MODULE__, :start_hydraulic_controller,
                 [[name: hydraulic_controller(ws)] ++ hopts, daq2]}
            }
          ]
      end

    Supervisor.init([{Plant, plant_opts}] ++ daqs ++ hydraulic, strategy: :rest_for_one)
  end

  @doc false
  def start_hydraulic_controller(opts, daq2) do
    HydraulicController.start_link(Keyword.put_new(opts, :daq2, DAQ.endpoint(daq2)))
  end

  defp name(ws, role), do: {:via, Registry, {Vws.Registry, {ws, role}}}
end
