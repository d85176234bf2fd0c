defmodule Vws.Sim.Floor do
  @moduledoc """
  The simulated shop floor of one workstation: the plant (`Vws.Sim.Plant`), the two
  data-acquisition units on it (`Vws.Sim.DAQ`, each listening on its own endpoint) and — when
  asked — the hydraulic controller's program (`Vws.Peers.HydraulicController`) on DAQ #2, the GE-2000
  (`Vws.Sim.GE2000`), the VAL II robot (`Vws.Sim.VAL2`) and the material-handling system
  (`Vws.Sim.MHS`), wired to the plant as the real equipment is to the workstation:

  ```
  Vws.Sim.Floor (rest_for_one)
  ├── Vws.Sim.Plant        {ws, :sim_plant}   — other simulators find it with plant/1
  ├── Vws.Sim.DAQ (DAQ #1) {ws, :sim_daq1}    — on :daq1 (default tcp://127.0.0.1:0); `daq1: false`: none
  ├── Vws.Sim.DAQ (DAQ #2) {ws, :sim_daq2}    — the pallet's channels, on :daq2 (default tcp://127.0.0.1:0)
  ├── the hydraulic controller       named {:sim_floor, ws}, on DAQ #2 — option :hydraulic
  ├── Vws.Sim.GE2000       {ws, :sim_ge2000}  — option :ge2000
  ├── Vws.Sim.VAL2         {ws, :sim_val2}    — option :robot
  └── Vws.Sim.MHS          {ws, :sim_mhs}     — option :mhs
  ```

  The hydraulic controller is not a simulator — it is the controller itself, a peer — but on
  the simulated floor it has nowhere else to run; it comes after DAQ #2, which it needs. The
  floor does not name it: whoever puts the floor together hands it the controller's module
  (`hydraulic: {Vws.Peers.HydraulicController, opts}`), as the simulators sit below the peers.

  The wires, so that the plant's collision oracle (`Vws.Sim.Plant.collisions/1`) sees what the
  equipment does without asking the CEC:

    * the cycle-start relay of DAQ #1 drives the GE-2000's cycle-start input
      (`Vws.Sim.GE2000.cycle_start_input/2`), and the GE-2000's cycle moves the table
      (`Vws.Sim.Plant.set_cycle/2`);
    * the robot's motions tell the plant where the gripper is (`on_move` →
      `Vws.Sim.Plant.set_robot/2`, the work volumes of `priv/sims/robot_locations.exs`);
    * the MHS moves the trays (`Vws.Sim.Plant.move_tray/3`) under the workstation's interlock.

  `Vws.Ops.Demo` starts the whole floor before the workstation and gives the workstation the
  links that reach `devices(ws)` (`Vws.Ops.Demo.shop_floor/1`); `mix vws.serve` starts the
  same floor, without the simulators of the devices it is pointed at (`--daq1`, `--hydraulic`,
  `--ge2000`, `--robot`). Both start it with `start_stocked/1`: the material handling on, a
  blank in tray #1. Pointing a device at real equipment instead needs no simulator for it. The
  floor says where its devices are (`devices/1`); what the workstation makes of them is the
  workstation's (`Vws.CEC.Workstation.device_links/3`).

      iex> {:ok, _floor} = Vws.Sim.Floor.start_link(workstation: "floor-doc", time_scale: 100)
      iex> Vws.Sim.Floor.daq1_endpoint("floor-doc") =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
      iex> Vws.Sim.Floor.daq2_endpoint("floor-doc") =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
      iex> Vws.Sim.Plant.snapshot(Vws.Sim.Floor.plant("floor-doc")).vise.jaw_mm
      150.0
  """
  use Supervisor

  alias Vws.Sim.{DAQ, GE2000, Line, MHS, Plant, VAL2}

  @doc """
  Starts the floor of workstation `:workstation`. Options:

    * `:time_scale` (default 1.0) — how many times faster than real time the plant runs; the
      GE-2000's cycle and the robot's motions are scaled with it;
    * `:seed`, `:plant` (more `Vws.Sim.Plant` options, e.g. `config:`);
    * `:on_relay` — `fun(signal, energised?)`, told of every actuator switched on or off after
      the floor's own wires (the plant's `:on_relay`; it runs in the plant's process and must
      not call the plant) — to watch the equipment, as a test does;
    * `:daq1` — the endpoint DAQ #1 listens on, default `"tcp://127.0.0.1:0"`; `false` for no
      DAQ #1; `:daq2` the same for DAQ #2;
    * `:hydraulic` — `{module, opts}` to run the hydraulic controller's program on DAQ #2:
      `module` is `Vws.Peers.HydraulicController` (or one with its `start_link/1`, `endpoint/1`
      and `await_ready/2`), `opts` its `start_link/1` options (default `false`: none);
    * `:ge2000` — `true` or `Vws.Sim.GE2000` options (default `cycle_time` 5 s / time scale,
      at least 4 s, so that MONARCH sees the machine run after it has let go of the button, even
      when a DNC reply is lost on the way);
    * `:robot` — `true` or `Vws.Sim.VAL2` options (default `time_scale` 1 / time scale);
    * `:mhs` — `true` or `Vws.Sim.MHS` options;
    * `:lines` — faulty cables (`Vws.Sim.Line`) on every link the floor's equipment is reached
      by: `[faults: [ber: 1.0e-4, …], seed: term]` puts one in front of DAQ #1, the hydraulic
      controller, the GE-2000 and the VAL II (the CEC's links) and one between the hydraulic
      controller and DAQ #2; `devices/1` then gives the lines' endpoints. Each line draws its
      faults from `{seed, link}`. `line/2` finds one (for `Vws.Sim.Line.info/1`,
      `set_faults/3`, `disconnect/1`). Default `false`: no lines.
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

  @doc "The name of the floor's hydraulic controller (for calls to its module, `Vws.Peers.HydraulicController`)."
  @spec hydraulic_controller(term) :: term
  def hydraulic_controller(ws), do: {:sim_floor, ws}

  @doc "Where the floor's hydraulic controller is reached by the CEC, as an endpoint string."
  @spec hydraulic_endpoint(term) :: String.t()
  def hydraulic_endpoint(ws), do: hydraulic_module(ws).endpoint(hydraulic_controller(ws))

  # the hydraulic controller's module, as the floor was given it (kept as the value of the
  # floor's registered name), nil when the floor has none
  defp hydraulic_module(ws) do
    case Registry.lookup(Vws.Registry, {ws, :sim_floor}) do
      [{_pid, %{hydraulic: module}}] -> module
      _ -> nil
    end
  end

  @doc "The GE-2000 simulator of a workstation's floor (a registered name)."
  @spec ge2000(term) :: GenServer.name()
  def ge2000(ws), do: name(ws, :sim_ge2000)

  @doc "The VAL II simulator of a workstation's floor (a registered name)."
  @spec robot(term) :: GenServer.name()
  def robot(ws), do: name(ws, :sim_val2)

  @doc "The material-handling system of a workstation's floor (a registered name)."
  @spec mhs(term) :: GenServer.name()
  def mhs(ws), do: name(ws, :sim_mhs)

  @doc """
  The faulty line of a link of the floor (`:daq1`, `:daq2`, `:hydraulic`, `:ge2000`, `:robot`),
  a registered name; the floor has them when started with `:lines`. (`Vws.Ops.Demo` registers
  the WC's line as `line(ws, :wc)`.)
  """
  @spec line(term, atom) :: GenServer.name()
  def line(ws, link), do: name(ws, {:line, link})

  @doc "The links of the floor that have a faulty line, with the line: `[{link, name}]`."
  @spec lines(term) :: [{atom, GenServer.name()}]
  def lines(ws) do
    for link <- [:wc, :daq1, :daq2, :hydraulic, :ge2000, :robot],
        running?(line(ws, link)),
        do: {link, line(ws, link)}
  end

  @doc """
  The `devices:` option of a workstation reaching every device of the floor:
  `[daq1: …, hydraulic: …, ge2000: …, robot: …]` (those started), through the floor's faulty
  lines where it has them.
  """
  @spec devices(term) :: keyword(String.t())
  def devices(ws) do
    for {device, sim, endpoint} <- [
          {:daq1, daq1(ws), &DAQ.endpoint/1},
          {:hydraulic, hydraulic_controller(ws),
           fn {:sim_floor, ws} -> hydraulic_endpoint(ws) end},
          {:ge2000, ge2000(ws), &GE2000.endpoint/1},
          {:robot, robot(ws), &VAL2.endpoint/1}
        ],
        running?(sim) do
      line = line(ws, device)

      if running?(line),
        do: {device, to_string(Line.endpoint(line))},
        else: {device, endpoint.(sim)}
    end
  end

  defp running?({:sim_floor, ws} = controller) do
    case hydraulic_module(ws) do
      nil -> false
      module -> module.endpoint(controller) != nil
    end
  catch
    :exit, _ -> false
  end

  defp running?(name), do: GenServer.whereis(name) != nil

  @doc """
  Starts the floor as `mix vws.demo` and `mix vws.serve` both have it — linked to the caller, or
  under the `DynamicSupervisor` given as `:supervisor` — and stocks it (`stock/1`): the
  equipment options as `start_link/1` takes them, with the material-handling system on unless
  `mhs: false`. It returns once the hydraulic controller (when on the floor) is ready and a
  blank lies in tray #1, so that `priv/sims/machining_cycle.vws` runs against either.
  """
  @spec start_stocked(keyword) :: {:ok, pid} | {:error, term}
  def start_stocked(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    {supervisor, floor} = Keyword.pop(opts, :supervisor)
    floor = Keyword.put_new(floor, :mhs, true)

    started =
      case supervisor do
        nil -> start_link(floor)
        supervisor -> DynamicSupervisor.start_child(supervisor, {__MODULE__, floor})
      end

    with {:ok, pid} <- started,
         :ok <- await_hydraulic(ws, floor[:hydraulic]),
         :ok <- stock(ws) do
      {:ok, pid}
    end
  end

  defp await_hydraulic(_ws, falsy) when falsy in [nil, false], do: :ok

  defp await_hydraulic(ws, {module, _opts}) do
    case module.await_ready(hydraulic_controller(ws), 10_000) do
      :ok -> :ok
      :timeout -> {:error, :hydraulic_controller_not_ready}
    end
  end

  @doc """
  The parts a floor starts with (the demo's and `mix vws.serve`'s): one blank in tray #1, the
  vise, the gripper and tray #2 empty.
  """
  @spec stock(term) :: :ok | {:error, term}
  def stock(ws), do: Plant.set_part(plant(ws), :tray1, true)

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    # the hydraulic controller's module, for hydraulic_endpoint/1 and devices/1: the value of
    # the floor's own name (this process registered it)
    with {module, _opts} <- Keyword.get(opts, :hydraulic, false) do
      {_, _} =
        Registry.update_value(Vws.Registry, {ws, :sim_floor}, fn _ -> %{hydraulic: module} end)
    end

    scale = Keyword.get(opts, :time_scale, 1.0)
    plant = plant(ws)

    wire =
      if opts[:ge2000] do
        ge = ge2000(ws)

        fn
          :cycle_start_relay, closed? -> GE2000.cycle_start_input(ge, closed?)
          _signal, _closed? -> :ok
        end
      end

    on_relay =
      case {wire, opts[:on_relay]} do
        {wire, nil} ->
          wire

        {nil, watcher} ->
          watcher

        {wire, watcher} ->
          fn signal, closed? ->
            wire.(signal, closed?)
            watcher.(signal, closed?)
          end
      end

    plant_opts =
      [name: plant, time_scale: scale, on_relay: on_relay] ++
        Keyword.take(opts, [:seed]) ++ Keyword.get(opts, :plant, [])

    lines = Keyword.get(opts, :lines, false)

    daqs =
      for daq <- [:daq1, :daq2], Keyword.get(opts, daq) != false do
        endpoint = Keyword.get(opts, daq, "tcp://127.0.0.1:0")
        {DAQ, plant: plant, name: name(ws, :"sim_#{daq}"), daq: daq, endpoint: endpoint}
      end

    # DAQ #2's line comes before the hydraulic controller, which dials through it; the CEC's
    # lines come last, when every simulator listens (a restarted line restarts no equipment)
    children =
      [{Plant, plant_opts}] ++
        daqs ++
        line_children(ws, lines, [{:daq2, daq2(ws), &DAQ.endpoint/1}]) ++
        hydraulic_child(ws, Keyword.get(opts, :hydraulic, false)) ++
        ge2000_child(ws, opts[:ge2000], scale) ++
        robot_child(ws, opts[:robot], scale) ++
        mhs_child(ws, opts[:mhs]) ++
        line_children(ws, lines, [
          {:daq1, daq1(ws), &DAQ.endpoint/1},
          {:hydraulic, hydraulic_controller(ws),
           fn {:sim_floor, ws} -> hydraulic_endpoint(ws) end},
          {:ge2000, ge2000(ws), &GE2000.endpoint/1},
          {:robot, robot(ws), &VAL2.endpoint/1}
        ])

    Supervisor.init(children, strategy: :rest_for_one)
  end

  defp line_children(_ws, false, _links), do: []

  defp line_children(ws, lines, links) do
    for {link, sim, endpoint} <- links do
      line_opts = [
        name: line(ws, link),
        seed: {Keyword.get(lines, :seed, 0), link},
        faults: Keyword.get(lines, :faults, [])
      ]

      %{id: {Line, link}, start: {__MODULE__, :start_line, [line_opts, sim, endpoint]}}
    end
  end

  @doc false
  # A line to a simulator that is not on this floor is not started.
  def start_line(opts, sim, endpoint) do
    if running?(sim), do: Line.start_link([target: endpoint.(sim)] ++ opts), else: :ignore
  end

  defp hydraulic_child(_ws, falsy) when falsy in [nil, false], do: []

  defp hydraulic_child(ws, {module, hopts}) when is_atom(module) and is_list(hopts) do
    [
      %{
        id: :hydraulic_controller,
        type: :supervisor,
        # DAQ #2 listens before the controller starts: its endpoint is known by then
        start:
          {__MODULE__, :start_hydraulic_controller,
           [module, [name: hydraulic_controller(ws)] ++ hopts, ws]}
      }
    ]
  end

  defp hydraulic_child(_ws, other) do
    raise ArgumentError,
          "hydraulic: takes {module, options} (Vws.Peers.HydraulicController and its " <>
            "start_link/1 options), got #{inspect(other)}"
  end

  @doc false
  def start_hydraulic_controller(module, opts, ws) do
    daq2 =
      if running?(line(ws, :daq2)),
        do: to_string(Line.endpoint(line(ws, :daq2))),
        else: DAQ.endpoint(daq2(ws))

    module.start_link(Keyword.put_new(opts, :daq2, daq2))
  end

  defp ge2000_child(_ws, falsy, _scale) when falsy in [nil, false], do: []

  defp ge2000_child(ws, spec, scale) do
    plant = plant(ws)
    # at least 4 s, however fast the floor runs: MONARCH looks for the cycle after letting go of
    # the button (200 ms) by reading the machine's status over the DNC link, and one reply lost
    # on a noisy line costs it 3 s (`reply_timeout`) — a shorter cycle could be over unseen
    cycle = if scale > 0, do: max(round(5_000 / scale), 4_000), else: 5_000

    defaults = [
      id: GE2000,
      name: ge2000(ws),
      cycle_time: cycle,
      plant: fn event -> Plant.set_cycle(plant, event == :table_out_of_park) end
    ]

    [{GE2000, Keyword.merge(defaults, options(spec))}]
  end

  defp robot_child(_ws, falsy, _scale) when falsy in [nil, false], do: []

  defp robot_child(ws, spec, scale) do
    plant = plant(ws)

    defaults = [
      id: VAL2,
      name: robot(ws),
      time_scale: if(scale > 0, do: 1 / scale, else: 1.0),
      on_move: fn %{volume: volume} -> Plant.set_robot(plant, %{volume: volume}) end
    ]

    [{VAL2, Keyword.merge(defaults, options(spec))}]
  end

  defp mhs_child(_ws, falsy) when falsy in [nil, false], do: []

  defp mhs_child(ws, spec) do
    defaults = [name: mhs(ws), workstation: ws, plant: plant(ws)]
    [{MHS, Keyword.merge(defaults, options(spec))}]
  end

  defp options(true), do: []
  defp options(opts) when is_list(opts), do: opts

  defp name(ws, role), do: Vws.Names.via(ws, role)
end
