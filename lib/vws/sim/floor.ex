defmodule Vws.Sim.Floor do
  @moduledoc """
  The simulated shop floor of one workstation, as far as DAQ #1 reaches it: the plant
  (`Vws.Sim.Plant`) and the DAQ #1 simulator (`Vws.Sim.DAQ`) listening on its own endpoint.

  ```
  Vws.Sim.Floor (rest_for_one)
  ├── Vws.Sim.Plant       {ws, :sim_plant} in Vws.Registry — other simulators find it with plant/1
  └── Vws.Sim.DAQ (DAQ #1) {ws, :sim_daq1}  — on :daq1 (default tcp://127.0.0.1:0)
  ```

  `mix vws.serve` and `Vws.Demo` start it before the workstation and give the workstation
  `devices: [daq1: Vws.Sim.Floor.daq1_endpoint(ws)]`; pointing `daq1` at a real instrument instead
  needs no floor at all.

      iex> {:ok, _floor} = Vws.Sim.Floor.start_link(workstation: "floor-doc", time_scale: 100)
      iex> Vws.Sim.Floor.daq1_endpoint("floor-doc") =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
      iex> Vws.Sim.Plant.snapshot(Vws.Sim.Floor.plant("floor-doc")).vise.jaw_mm
      150.0
  """
  use Supervisor

  alias Vws.Sim.{DAQ, Plant}

  @doc """
  Starts the floor of workstation `:workstation`. Options: `:time_scale` (default 1.0), `:seed`,
  `:plant` (more `Vws.Sim.Plant` options, e.g. `config:`), `:daq1` (the endpoint DAQ #1 listens
  on, default `"tcp://127.0.0.1:0"`).
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

  @doc """
  For `Vws.Demo`'s shop floor: starts the floor (linked to the caller) with the demo's
  `:workstation` and `:time_scale`, and returns the workstation links and partition options
  that reach it (`Vws.Partitions.VwsStatus.wiring/3`).
  """
  @spec shop_floor(keyword) ::
          {:ok, %{name: String.t(), links: [Supervisor.child_spec()], partitions: keyword}}
          | {:error, term}
  def shop_floor(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    with {:ok, _pid} <- start_link(Keyword.take(opts, [:workstation, :time_scale, :seed])) do
      wiring = Vws.Partitions.VwsStatus.wiring(ws, daq1_endpoint(ws))
      {:ok, %{name: "plant + DAQ #1", links: wiring.links, partitions: wiring.partitions}}
    end
  end

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    plant_opts =
      [name: plant(ws), time_scale: Keyword.get(opts, :time_scale, 1.0)] ++
        Keyword.take(opts, [:seed]) ++ Keyword.get(opts, :plant, [])

    children = [
      {Plant, plant_opts},
      {DAQ,
       plant: plant(ws),
       name: daq1(ws),
       daq: :daq1,
       endpoint: Keyword.get(opts, :daq1, "tcp://127.0.0.1:0")}
    ]

    Supervisor.init(children, strategy: :rest_for_one)
  end

  defp name(ws, role), do: {:via, Registry, {Vws.Registry, {ws, role}}}
end
