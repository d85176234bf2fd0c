defmodule Vws.Sim.Plant do
  @moduledoc """
  The simulated shop floor of one workstation: vise, gripper and indexer, vacuum, the two trays,
  the machine table, the pallet and the cycle-start relay, seen through the channels of DAQ #1
  and DAQ #2 as mapped in `priv/plant.exs` (`Vws.Links.DAQ.ChannelMap`).

  The DAQ simulators call `read_voltage/3`, `read_resistance/3`, `close_channel/3`,
  `open_channel/3` and `channel_closed?/3`, one per SCPI query; the robot and GE-2000 simulators
  and the material-handling system call `set_robot/2`, `set_cycle/2` and `move_tray/3`; tests
  inject faults and read the truth with `snapshot/1` and `collisions/1`. The physics is
  `Vws.Sim.Plant.Model`.

      iex> {:ok, plant} = Vws.Sim.Plant.start_link(time_scale: 0, seed: 7)
      iex> :ok = Vws.Sim.Plant.set_part(plant, :vise, true)
      iex> :ok = Vws.Sim.Plant.close_channel(plant, 206)
      iex> :ok = Vws.Sim.Plant.advance(plant, 2.0)
      iex> %{jaw_mm: 50.0, force_n: 2000.0, part_present: true} =
      ...>   Map.take(Vws.Sim.Plant.snapshot(plant).vise, [:jaw_mm, :force_n, :part_present])
      iex> {:ok, ohms} = Vws.Sim.Plant.read_resistance(plant, 117)
      iex> abs(ohms - 370.0) <= 0.05
      true

  ## Time

  The plant keeps no timer. Before each call it advances its model by the real time elapsed
  since the previous call multiplied by `:time_scale` (so `time_scale: 1000` runs a 1.5 s vise
  stroke in 1.5 ms). `advance/2` adds simulated seconds on top; with `time_scale: 0` the plant
  moves only when told, which makes a test exact.

  ## Channels

  A channel is its number on DAQ #1 (`117`) or `{daq, number}` (`{:daq2, 103}`).
  """
  use GenServer

  alias Vws.Links.DAQ.ChannelMap
  alias Vws.Sim.Plant.Model

  @type plant :: GenServer.server()
  @type channel :: pos_integer | {ChannelMap.daq(), pos_integer}
  @type channel_error :: :unknown_channel | :not_a_sensor | :not_an_actuator

  @doc false
  def child_spec(opts) do
    %{id: {__MODULE__, Keyword.get(opts, :name)}, start: {__MODULE__, :start_link, [opts]}}
  end

  @doc """
  Starts a plant. Options:

    * `:name` — a GenServer name (any number of plants may run on a node);
    * `:time_scale` — simulated seconds per real second (default 1.0; 0 = only `advance/2`);
    * `:config` — a path, or a map merged over `priv/plant.exs` (default: that file);
    * `:seed` — seeds the sensor noise (default 0), so runs are repeatable;
    * `:on_relay` — `fun(signal, energised?)`, called when an actuator's device is switched on or
      off (a relay, or a stuck valve coming free): the wire to equipment outside the plant, such
      as the GE-2000's cycle-start input (`Vws.Sim.Floor`). It runs in the plant's process, so it
      must not call the plant: send a message.
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts \\ []) do
    gen_opts = if name = opts[:name], do: [name: name], else: []
    GenServer.start_link(__MODULE__, opts, gen_opts)
  end

  @doc "DC volts on a sensor channel (`MEAS:VOLT:DC?`), with noise."
  @spec read_voltage(plant, channel) :: {:ok, float} | {:error, channel_error}
  def read_voltage(plant, channel), do: call(plant, {:read_voltage, address(channel)})

  @doc "Ohms on a channel (`MEAS:RES?`), with noise; `overload` where nothing reads as a resistance."
  @spec read_resistance(plant, channel) :: {:ok, float} | {:error, channel_error}
  def read_resistance(plant, channel), do: call(plant, {:read_resistance, address(channel)})

  @doc "Closes an actuator relay (`ROUT:CLOS`)."
  @spec close_channel(plant, channel) :: :ok | {:error, channel_error}
  def close_channel(plant, channel), do: call(plant, {:close_channel, address(channel)})

  @doc "Opens an actuator relay (`ROUT:OPEN`)."
  @spec open_channel(plant, channel) :: :ok | {:error, channel_error}
  def open_channel(plant, channel), do: call(plant, {:open_channel, address(channel)})

  @doc "Whether an actuator relay is closed (`ROUT:CLOS?`)."
  @spec channel_closed?(plant, channel) :: {:ok, boolean} | {:error, channel_error}
  def channel_closed?(plant, channel), do: call(plant, {:channel_closed?, address(channel)})

  @doc "Opens every relay of one DAQ, as its `*RST` does."
  @spec open_all(plant, ChannelMap.daq()) :: :ok
  def open_all(plant, daq \\ :daq1), do: call(plant, {:open_all, daq})

  @doc """
  Injects a fault. Each has its own physical symptom:

    * `:stuck_valve`, `actuator: signal` — the valve (or relay, solenoid) stays as it was:
      its relay still answers `ROUT:CLOS?` but the device behind it does not move;
    * `:broken_switch`, `switch: signal` — that switch reads open forever;
    * `:no_part`, `where: :vise | :gripper` — it closes on nothing: vise jaws to 0 mm with no
      force and no part-present, gripper fingers to 0 mm;
    * `:weak_clamp`, `where: :vise | :pallet, force_n: n` — the clamp force stops at `n`;
    * `:sensor_open_circuit`, `channel: n` (with `daq:`, default `:daq1`) or `signal: name` —
      the channel reads `overload` (9.9e37) for volts and ohms.

  Signals are the names of `priv/plant.exs` (`:vise_close_valve`, `:table_park`, …).
  """
  @spec inject_fault(plant, Model.fault(), keyword) ::
          :ok | {:error, :unknown_fault | :bad_options}
  def inject_fault(plant, fault, opts \\ []), do: call(plant, {:inject_fault, fault, opts})

  @doc "Clears every fault of one kind (`:all` clears all)."
  @spec clear_fault(plant, Model.fault() | :all) :: :ok
  def clear_fault(plant, fault), do: call(plant, {:clear_fault, fault})

  @doc """
  Puts a part at `:vise`, `:gripper`, `:tray1` or `:tray2` (`true`, or a width in mm) or removes
  it (`false`). `{:error, :no_room}` when the jaws or fingers are narrower than the part.
  """
  @spec set_part(plant, Model.where(), boolean | number) :: :ok | {:error, :no_room | :bad_place}
  def set_part(plant, where, present), do: call(plant, {:set_part, where, present})

  @doc """
  Where the robot's gripper is: `%{volume: :safe | :table | :vise | :pallet | :tray1 | :tray2 |
  atom}`, with optional `carrying: boolean` to put a part in the gripper or take it out.
  """
  @spec set_robot(plant, map) :: :ok
  def set_robot(plant, %{volume: volume} = robot) when is_atom(volume),
    do: call(plant, {:set_robot, robot})

  @doc "A machining cycle starts (`true`) or ends (`false`); the table leaves park meanwhile."
  @spec set_cycle(plant, boolean) :: :ok
  def set_cycle(plant, running?) when is_boolean(running?),
    do: call(plant, {:set_cycle, running?})

  @doc "Tool changer 1's fingers release (`true`) or hold their tool (`false`): the CHANGER_1 switch."
  @spec set_changer1(plant, boolean) :: :ok
  def set_changer1(plant, released?) when is_boolean(released?),
    do: call(plant, {:set_changer1, released?})

  @doc "The material-handling system moves tray 1 or 2 in or out; refused while it is locked."
  @spec move_tray(plant, 1 | 2, :in | :out) :: :ok | {:error, :locked}
  def move_tray(plant, tray, direction) when tray in [1, 2] and direction in [:in, :out],
    do: call(plant, {:move_tray, tray, direction})

  @doc "Runs the plant on by `seconds` of simulated time at once."
  @spec advance(plant, number) :: :ok
  def advance(plant, seconds) when is_number(seconds) and seconds >= 0,
    do: call(plant, {:advance, seconds})

  @doc "The true physical state (mm, degrees, N, switch states, parts, relays, faults)."
  @spec snapshot(plant) :: map
  def snapshot(plant), do: call(plant, :snapshot)

  @doc "Physical conflicts recorded so far, oldest first (see `Vws.Sim.Plant.Model`)."
  @spec collisions(plant) :: [Model.collision()]
  def collisions(plant), do: call(plant, :collisions)

  @doc """
  Every relay write the plant obeyed so far (`ROUT:CLOS`/`ROUT:OPEN`, and each relay an `*RST`
  opened), per channel: `%{{daq, channel} => %{close: n, open: n}}`. A write counts even when
  the relay was already where it was told to go: it is what the equipment was commanded to do,
  so a test can tell that a command did not run twice.
  """
  @spec writes(plant) :: %{
          {ChannelMap.daq(), pos_integer} => %{close: non_neg_integer, open: non_neg_integer}
        }
  def writes(plant), do: call(plant, :writes)

  @doc "The loaded channel map and constants."
  @spec config(plant) :: ChannelMap.t()
  def config(plant), do: call(plant, :config)

  defp call(plant, request), do: GenServer.call(plant, request)

  defp address({daq, number}) when daq in [:daq1, :daq2] and is_integer(number), do: {daq, number}
  defp address(number) when is_integer(number), do: {:daq1, number}

  ## Server

  @impl true
  def init(opts) do
    # equipment: its own machine, which the CEC's load does not slow (see Vws.Sim.DAQ)
    Process.flag(:priority, :high)
    config = ChannelMap.load(Keyword.get(opts, :config, ChannelMap.default_path()))
    scale = Keyword.get(opts, :time_scale, 1.0)

    unless is_number(scale) and scale >= 0 do
      raise ArgumentError, "time_scale must be a number >= 0, got #{inspect(scale)}"
    end

    {:ok,
     %{
       model: Model.new(config, Keyword.get(opts, :seed, 0)),
       # the workstation in a {:via, Registry, {Vws.Registry, {ws, role}}} name, for telemetry
       workstation: Vws.Names.id_of(Keyword.get(opts, :name)),
       time_scale: scale,
       last: now(),
       on_relay: Keyword.get(opts, :on_relay),
       writes: %{}
     }}
  end

  @impl true
  def handle_call(:writes, _from, state), do: {:reply, state.writes, state}

  def handle_call(request, _from, state) do
    now = now()
    dt = (now - state.last) / 1_000_000 * state.time_scale
    state = %{state | model: Model.advance(state.model, dt), last: now}
    {reply, model} = handle(request, state.model)
    notify_relays(state.on_relay, state.model, model)

    # one account of the relay writes serves both Plant.writes/1 and the telemetry event, so
    # they cannot disagree (an *RST's openings are writes too)
    writes =
      for {address, kind} <- relay_writes(request, reply, model), reduce: state.writes do
        acc ->
          written(address, kind, state)
          count_write(acc, address, kind)
      end

    {:reply, reply, %{state | model: model, writes: writes}}
  end

  # The relays a request wrote, `[{address, :close | :open}]`: what the equipment was told to
  # do, whether or not it changed anything.
  defp relay_writes({route, address}, :ok, _model)
       when route in [:close_channel, :open_channel],
       do: [{address, if(route == :close_channel, do: :close, else: :open)}]

  defp relay_writes({:open_all, daq}, :ok, model) do
    for {{^daq, _} = address, %{kind: :actuator}} <- model.config.channels,
        do: {address, :open}
  end

  defp relay_writes(_request, _reply, _model), do: []

  defp count_write(writes, address, kind) do
    Map.update(
      writes,
      address,
      Map.put(%{close: 0, open: 0}, kind, 1),
      &Map.update!(&1, kind, fn n -> n + 1 end)
    )
  end

  defp written({daq, channel} = address, kind, state) do
    signal =
      case ChannelMap.entry(state.model.config, address) do
        %{signal: signal} -> signal
        _ -> nil
      end

    Vws.Telemetry.execute([:vws, :sim, :plant, :actuator], %{count: 1}, %{
      workstation: state.workstation,
      daq: daq,
      channel: channel,
      signal: signal,
      action: kind
    })
  end

  defp notify_relays(nil, _before, _after), do: :ok

  defp notify_relays(fun, before, after_) do
    was = Model.energised(before)
    now = Model.energised(after_)

    for signal <- MapSet.difference(now, was), do: fun.(signal, true)
    for signal <- MapSet.difference(was, now), do: fun.(signal, false)
    :ok
  end

  defp handle({:read_voltage, {daq, n}}, m), do: Model.read_voltage(m, daq, n)
  defp handle({:read_resistance, {daq, n}}, m), do: Model.read_resistance(m, daq, n)
  defp handle({:close_channel, {daq, n}}, m), do: Model.close_channel(m, daq, n)
  defp handle({:open_channel, {daq, n}}, m), do: Model.open_channel(m, daq, n)
  defp handle({:channel_closed?, {daq, n}}, m), do: {Model.channel_closed?(m, daq, n), m}
  defp handle({:open_all, daq}, m), do: {:ok, Model.open_all(m, daq)}
  defp handle({:inject_fault, fault, opts}, m), do: ok(Model.inject_fault(m, fault, opts), m)
  defp handle({:clear_fault, fault}, m), do: {:ok, Model.clear_fault(m, fault)}
  defp handle({:set_part, where, present}, m), do: ok(Model.set_part(m, where, present), m)
  defp handle({:set_robot, robot}, m), do: {:ok, Model.set_robot(m, robot)}
  defp handle({:set_cycle, running?}, m), do: {:ok, Model.set_cycle(m, running?)}
  defp handle({:set_changer1, released?}, m), do: {:ok, Model.set_changer1(m, released?)}
  defp handle({:move_tray, tray, dir}, m), do: ok(Model.move_tray(m, tray, dir), m)
  defp handle({:advance, seconds}, m), do: {:ok, Model.advance(m, seconds)}
  defp handle(:snapshot, m), do: {Model.snapshot(m), m}
  defp handle(:collisions, m), do: {Model.collisions(m), m}
  defp handle(:config, m), do: {m.config, m}

  defp ok({:ok, model}, _old), do: {:ok, model}
  defp ok({:error, _} = error, old), do: {error, old}

  defp now, do: System.monotonic_time(:microsecond)
end
