defmodule Vws.Sim.Plant.Model do
  @moduledoc """
  The physics of the plant, as a pure value: `Vws.Sim.Plant` keeps one and advances it by the
  simulated time elapsed before each call. Nothing here reads a clock; tests may drive it with
  exact time steps.

      iex> m = Vws.Sim.Plant.Model.new(Vws.Links.DAQ.ChannelMap.load(), 1)
      iex> {:ok, m} = Vws.Sim.Plant.Model.close_channel(m, :daq1, 206)
      iex> m = Vws.Sim.Plant.Model.advance(m, 2.0)
      iex> Vws.Sim.Plant.Model.snapshot(m).vise.jaw_mm
      0.0

  ## How the plant moves

  Every moving thing goes at a constant rate towards a target set by its actuators (a full
  stroke takes the configured time):

    * vise — OPEN valve: force drops to 0 and the jaws open to `vise_max_mm`; CLOSE valve: the
      jaws close to the part's width (a part on the seat, or one the gripper holds between them),
      then the force rises to `vise_clamp_n`; with no part they close to 0 mm against their stop,
      which takes the load, so the force gauge stays at 0. Neither or both valves: the vise holds
      jaws and force.
    * gripper — OPEN/CLOSE solenoids as the vise; closing stops on a part between the fingers,
      else the fingers close on each other (0 mm). The indexer turns to `(bit1 * 2 + bit0) * 90`
      degrees.
    * vacuum — the pressure switch closes `vacuum_s` after the motor starts.
    * trays — moved in or out by the material-handling system (`move_tray/3`), refused while
      the tray's lock relay is closed.
    * table — leaves park while a cycle runs (`set_cycle/2`) and returns after.
    * pallet — rams extend while their valves are on (the X/Y switch closes at full stroke);
      each swing clamp swings onto the pallet and then builds `pallet_clamp_n`.

  Parts move between the vise, the trays and the gripper where the robot is (`set_robot/2`):
  fingers closing on a part in a tray, or in a vise whose jaws are off it, take it; vise jaws
  closing on a part the gripper holds take it; fingers opening put it down where the robot is,
  or drop it (a `:part_dropped` collision) if there is no free place there.

  ## Collisions

  Recorded once per episode, in order, each `%{kind, at_s, detail}`:

    * `:robot_in_table_volume` — the robot in a table volume (`table_volumes`) while the table
      is out of park or a cycle runs (seed §2.3.8, 1a/1b);
    * `:tray_moved_with_robot` — a tray moving while the robot is in its volume (2a/2b);
    * `:vise_opened_during_cycle` — the vise opening (jaws or force moving) during a cycle (3a);
    * `:cycle_started_vise_not_released` — a cycle started while the vise was still moving (3b);
    * `:part_dropped` — the gripper opened on a part with no free place under it.
  """

  alias Vws.Links.DAQ.ChannelMap

  @eps 1.0e-6

  @type daq :: ChannelMap.daq()
  @type where :: :vise | :gripper | :tray1 | :tray2
  @type fault :: :stuck_valve | :broken_switch | :no_part | :weak_clamp | :sensor_open_circuit
  @type collision :: %{kind: atom, at_s: float, detail: map}

  @type t :: %__MODULE__{
          config: ChannelMap.t(),
          rand: :rand.state(),
          t: float,
          relays: MapSet.t(ChannelMap.address()),
          faults: %{{fault, term} => map},
          vise: %{jaw_mm: float, force_n: float},
          gripper: %{finger_mm: float, indexer_deg: float},
          vacuum: float,
          trays: %{1 => %{mm: float, target_mm: float}, 2 => %{mm: float, target_mm: float}},
          table_mm: float,
          cycle: boolean,
          changer1_released: boolean,
          pallet: map,
          robot: atom,
          parts: %{where => float | nil},
          collisions: [collision],
          conflicts: MapSet.t()
        }

  defstruct [
    :config,
    :rand,
    :vise,
    :gripper,
    :trays,
    t: 0.0,
    relays: MapSet.new(),
    faults: %{},
    vacuum: 0.0,
    table_mm: 0.0,
    cycle: false,
    changer1_released: true,
    pallet: %{
      ram_x_mm: 0.0,
      ram_y_mm: 0.0,
      swing1_deg: 0.0,
      swing2_deg: 0.0,
      force1_n: 0.0,
      force2_n: 0.0
    },
    robot: :safe,
    parts: %{vise: nil, gripper: nil, tray1: nil, tray2: nil},
    collisions: [],
    conflicts: MapSet.new()
  ]

  @doc """
  A plant at rest: vise and gripper fully open, indexer at 0°, vacuum off, both trays in
  position and unlocked, table parked, pallet rams retracted and clamps released, no parts,
  robot in `:safe`. `seed` makes the sensor noise reproducible.
  """
  @spec new(ChannelMap.t(), integer) :: t
  def new(config, seed) do
    m = config.motion
    travel = m.tray_travel_mm * 1.0

    %__MODULE__{
      config: config,
      rand: :rand.seed_s(:exsss, seed),
      vise: %{jaw_mm: m.vise_max_mm * 1.0, force_n: 0.0},
      gripper: %{finger_mm: m.gripper_max_mm * 1.0, indexer_deg: 0.0},
      trays: %{1 => %{mm: travel, target_mm: travel}, 2 => %{mm: travel, target_mm: travel}}
    }
  end

  ## Time

  @doc "Moves everything on by `dt` simulated seconds, then hands parts over and checks conflicts."
  @spec advance(t, number) :: t
  def advance(%__MODULE__{} = m, dt) when dt <= 0, do: settle(m)

  def advance(%__MODULE__{} = m, dt) do
    %{m | t: m.t + dt}
    |> move_vise(dt)
    |> move_gripper(dt)
    |> move_simple(dt)
    |> move_pallet(dt)
    |> settle()
  end

  defp move_vise(m, dt) do
    mo = m.config.motion
    rate = mo.vise_max_mm / positive(mo.vise_stroke_s)
    %{jaw_mm: jaw, force_n: force} = m.vise

    vise =
      case vise_drive(m) do
        :open ->
          {jaw, _} = approach(jaw, mo.vise_max_mm, rate, dt)
          %{jaw_mm: jaw, force_n: 0.0}

        :close ->
          width = vise_obstacle(m)
          {jaw, left} = approach(jaw, width || 0.0, rate, dt)

          force =
            if width && left > 0 do
              force_rate = mo.vise_clamp_n / positive(mo.vise_force_rise_s)
              elem(approach(force, clamp_target(m, :vise), force_rate, left), 0)
            else
              force
            end

          %{jaw_mm: jaw, force_n: force}

        :hold ->
          m.vise
      end

    %{m | vise: vise}
  end

  defp move_gripper(m, dt) do
    mo = m.config.motion
    rate = mo.gripper_max_mm / positive(mo.gripper_stroke_s)
    finger = m.gripper.finger_mm

    finger =
      case gripper_drive(m) do
        :open -> elem(approach(finger, mo.gripper_max_mm, rate, dt), 0)
        :close -> elem(approach(finger, finger_obstacle(m) || 0.0, rate, dt), 0)
        :hold -> finger
      end

    index_rate = 90.0 / positive(mo.indexer_s_per_90)
    {deg, _} = approach(m.gripper.indexer_deg, indexer_target(m), index_rate, dt)
    %{m | gripper: %{finger_mm: finger, indexer_deg: deg}}
  end

  defp move_simple(m, dt) do
    mo = m.config.motion
    vacuum_target = if actuator?(m, :vacuum_motor), do: 1.0, else: 0.0
    {vacuum, _} = approach(m.vacuum, vacuum_target, 1.0 / positive(mo.vacuum_s), dt)

    tray_rate = mo.tray_travel_mm / positive(mo.tray_s)

    trays =
      Map.new(m.trays, fn {n, tray} ->
        {n, %{tray | mm: elem(approach(tray.mm, tray.target_mm, tray_rate, dt), 0)}}
      end)

    table_target = if m.cycle, do: mo.table_travel_mm, else: 0.0
    {table, _} = approach(m.table_mm, table_target, mo.table_travel_mm / positive(mo.table_s), dt)
    %{m | vacuum: vacuum, trays: trays, table_mm: table}
  end

  defp move_pallet(m, dt) do
    mo = m.config.motion
    p = m.pallet
    ram_rate = mo.ram_stroke_mm / positive(mo.ram_s)
    ram = fn mm, valve -> elem(approach(mm, on(m, valve, mo.ram_stroke_mm), ram_rate, dt), 0) end

    {swing1, force1} = move_swing_clamp(m, :swing_clamp1_valve, p.swing1_deg, p.force1_n, dt)
    {swing2, force2} = move_swing_clamp(m, :swing_clamp2_valve, p.swing2_deg, p.force2_n, dt)

    %{
      m
      | pallet: %{
          ram_x_mm: ram.(p.ram_x_mm, :ram_x_valve),
          ram_y_mm: ram.(p.ram_y_mm, :ram_y_valve),
          swing1_deg: swing1,
          swing2_deg: swing2,
          force1_n: force1,
          force2_n: force2
        }
    }
  end

  defp move_swing_clamp(m, valve, swing, force, dt) do
    mo = m.config.motion
    swing_rate = mo.swing_deg / positive(mo.swing_s)

    if actuator?(m, valve) do
      {swing, left} = approach(swing, mo.swing_deg, swing_rate, dt)
      force_rate = mo.pallet_clamp_n / positive(mo.pallet_force_rise_s)
      {force, _} = approach(force, clamp_target(m, :pallet), force_rate, left)
      {swing, force}
    else
      {elem(approach(swing, 0.0, swing_rate, dt), 0), 0.0}
    end
  end

  # Goes from `pos` towards `target` at `rate` per second for `dt` seconds; returns the new
  # position and the time left over after arriving (0 if it did not arrive).
  defp approach(pos, target, rate, dt) do
    distance = abs(target - pos)
    needed = distance / rate

    cond do
      distance == 0 -> {target * 1.0, dt}
      dt >= needed -> {target * 1.0, dt - needed}
      target > pos -> {pos + rate * dt, 0.0}
      true -> {pos - rate * dt, 0.0}
    end
  end

  defp positive(seconds), do: max(seconds * 1.0, 1.0e-9)

  ## Parts, obstacles and hand-overs

  # A part as the plant feels it: a :no_part fault makes a place close on nothing.
  defp part(m, where) do
    if Map.has_key?(m.faults, {:no_part, where}), do: nil, else: m.parts[where]
  end

  # A part the gripper can reach where the robot is, that is not already in the gripper.
  defp reachable_part(m) do
    case m.robot do
      :vise -> part(m, :vise)
      :tray1 -> if tray_in?(m, 1), do: part(m, :tray1)
      :tray2 -> if tray_in?(m, 2), do: part(m, :tray2)
      _ -> nil
    end
  end

  defp vise_obstacle(m) do
    width = part(m, :vise) || (m.robot == :vise && part(m, :gripper)) || nil
    if width && m.vise.jaw_mm >= width - @eps, do: width
  end

  defp finger_obstacle(m) do
    if Map.has_key?(m.faults, {:no_part, :gripper}) do
      nil
    else
      width = part(m, :gripper) || reachable_part(m)
      if width && m.gripper.finger_mm >= width - @eps, do: width
    end
  end

  defp settle(m), do: m |> hand_over() |> check_conflicts()

  defp hand_over(m) do
    fingers = m.gripper.finger_mm
    drive = gripper_drive(m)
    held = part(m, :gripper)
    here = reachable_part(m)

    cond do
      # fingers closed on a part that is free to come: take it
      drive == :close and held == nil and here != nil and near(fingers, here) and
          (m.robot != :vise or m.vise.jaw_mm > here + @eps) ->
        move_part(m, m.robot, :gripper)

      # vise jaws closed on the part the gripper holds: the vise has it now
      m.robot == :vise and held != nil and part(m, :vise) == nil and vise_drive(m) == :close and
          near(m.vise.jaw_mm, held) ->
        move_part(m, :gripper, :vise)

      # fingers opened off a held part: put it down here, or drop it
      drive == :open and held != nil and fingers > held + @eps ->
        if free_place?(m, m.robot) do
          move_part(m, :gripper, m.robot)
        else
          m = %{m | parts: %{m.parts | gripper: nil}}
          record(m, :part_dropped, %{volume: m.robot, width_mm: held})
        end

      true ->
        m
    end
  end

  defp free_place?(m, :vise), do: m.parts.vise == nil
  defp free_place?(m, :tray1), do: m.parts.tray1 == nil and tray_in?(m, 1)
  defp free_place?(m, :tray2), do: m.parts.tray2 == nil and tray_in?(m, 2)
  defp free_place?(_m, _volume), do: false

  defp near(a, b), do: abs(a - b) <= @eps

  defp move_part(m, from, to) do
    %{m | parts: %{m.parts | to => m.parts[from], from => nil}}
  end

  ## Conflicts

  defp check_conflicts(m) do
    now = conflicts_now(m)

    m =
      now
      |> MapSet.difference(m.conflicts)
      |> Enum.sort()
      |> Enum.reduce(m, fn {kind, detail}, m -> record(m, kind, detail) end)

    %{m | conflicts: now}
  end

  defp conflicts_now(m) do
    table =
      if m.robot in m.config.table_volumes and (m.cycle or not table_parked?(m)),
        do: [{:robot_in_table_volume, %{volume: m.robot}}],
        else: []

    trays =
      for n <- [1, 2],
          m.robot == tray_volume(n),
          tray_moving?(m, n),
          do: {:tray_moved_with_robot, %{tray: n}}

    vise =
      if m.cycle and vise_drive(m) == :open and
           (m.vise.jaw_mm < m.config.motion.vise_max_mm or m.vise.force_n > 0),
         do: [{:vise_opened_during_cycle, %{}}],
         else: []

    MapSet.new(table ++ trays ++ vise)
  end

  defp record(m, kind, detail) do
    %{m | collisions: [%{kind: kind, at_s: m.t, detail: detail} | m.collisions]}
  end

  defp tray_volume(1), do: :tray1
  defp tray_volume(2), do: :tray2

  ## Derived state

  @doc """
  The actuators whose device is energised (a stuck valve counts as it is stuck, not as its relay
  says): what the equipment wired to the relays sees.
  """
  @spec energised(t) :: MapSet.t(atom)
  def energised(m) do
    for signal <- Map.fetch!(ChannelMap.signals(), :actuator),
        actuator?(m, signal),
        into: MapSet.new(),
        do: signal
  end

  defp actuator?(m, signal) do
    case Map.fetch(m.faults, {:stuck_valve, signal}) do
      {:ok, %{value: value}} -> value
      :error -> relay?(m, signal)
    end
  end

  defp relay?(m, signal) do
    case ChannelMap.channel(m.config, signal) do
      nil -> false
      address -> MapSet.member?(m.relays, address)
    end
  end

  defp on(m, signal, value), do: if(actuator?(m, signal), do: value * 1.0, else: 0.0)

  defp vise_drive(m), do: drive(actuator?(m, :vise_open_valve), actuator?(m, :vise_close_valve))

  defp gripper_drive(m),
    do: drive(actuator?(m, :gripper_open_solenoid), actuator?(m, :gripper_close_solenoid))

  defp drive(true, false), do: :open
  defp drive(false, true), do: :close
  defp drive(_, _), do: :hold

  defp indexer_target(m) do
    bits =
      if(actuator?(m, :indexer_bit1), do: 2, else: 0) +
        if(actuator?(m, :indexer_bit0), do: 1, else: 0)

    bits * 90.0
  end

  defp clamp_target(m, where) do
    full =
      if where == :vise, do: m.config.motion.vise_clamp_n, else: m.config.motion.pallet_clamp_n

    case Map.fetch(m.faults, {:weak_clamp, where}) do
      {:ok, %{force_n: weak}} -> min(weak, full) * 1.0
      :error -> full * 1.0
    end
  end

  defp table_parked?(m), do: m.table_mm <= @eps
  defp tray_in?(m, n), do: m.trays[n].mm >= m.config.motion.tray_travel_mm - @eps
  defp tray_moving?(m, n), do: m.trays[n].mm != m.trays[n].target_mm

  defp vise_moving?(m) do
    case vise_drive(m) do
      :open ->
        m.vise.jaw_mm < m.config.motion.vise_max_mm or m.vise.force_n > 0

      :close ->
        width = vise_obstacle(m)

        m.vise.jaw_mm > (width || 0.0) + @eps or
          (width != nil and m.vise.force_n < clamp_target(m, :vise) - @eps)

      :hold ->
        false
    end
  end

  # The true state of every switch, before faults.
  defp switch(m, signal) do
    mo = m.config.motion

    case signal do
      :vise_part_present -> part(m, :vise) != nil
      :vise_fully_open -> m.vise.jaw_mm >= mo.vise_max_mm - @eps
      :table_park -> table_parked?(m)
      :tray1_in -> tray_in?(m, 1)
      :tray2_in -> tray_in?(m, 2)
      :gripper_fully_open -> m.gripper.finger_mm >= mo.gripper_max_mm - @eps
      :indexer_0 -> indexed?(m, 0)
      :indexer_90 -> indexed?(m, 90)
      :indexer_180 -> indexed?(m, 180)
      :indexer_270 -> indexed?(m, 270)
      :vacuum_on -> m.vacuum >= 1.0
      :tray1_locked -> actuator?(m, :tray1_lock)
      :tray2_locked -> actuator?(m, :tray2_lock)
      :pallet_x -> m.pallet.ram_x_mm >= mo.ram_stroke_mm - @eps
      :pallet_y -> m.pallet.ram_y_mm >= mo.ram_stroke_mm - @eps
      :changer1_released -> m.changer1_released
    end
  end

  defp indexed?(m, deg),
    do: abs(m.gripper.indexer_deg - deg) <= m.config.motion.indexer_tolerance_deg

  defp quantity(m, :vise_jaw_mm), do: m.vise.jaw_mm
  defp quantity(m, :gripper_finger_mm), do: m.gripper.finger_mm
  defp quantity(m, :vise_force_n), do: m.vise.force_n
  defp quantity(m, :clamp1_force_n), do: m.pallet.force1_n
  defp quantity(m, :clamp2_force_n), do: m.pallet.force2_n

  ## DAQ channels

  @doc """
  The DC voltage on a sensor channel, with noise: a switch reads `closed_volts` or `open_volts`
  (a broken switch always `open_volts`), a potentiometer its position, a gauge or spare channel
  about 0 V. An open-circuit channel reads `overload` exactly. Actuator channels are not
  sensors.
  """
  @spec read_voltage(t, daq, integer) ::
          {{:ok, float} | {:error, :unknown_channel | :not_a_sensor}, t}
  def read_voltage(m, daq, channel) do
    address = {daq, channel}

    case ChannelMap.entry(m.config, address) do
      nil ->
        {{:error, :unknown_channel}, m}

      %{kind: :actuator} ->
        {{:error, :not_a_sensor}, m}

      entry ->
        if open_circuit?(m, address),
          do: {{:ok, m.config.overload}, m},
          else: noisy(m, ideal_volts(m, entry), volts_noise(m, entry))
    end
  end

  @doc """
  The resistance on a channel, with noise: a gauge reads `ohms_at_zero + ohms_per_newton * force`;
  any other sensor channel (powered, so no resistance reading) and an open-circuit gauge read
  `overload`. Actuator channels are not sensors.
  """
  @spec read_resistance(t, daq, integer) ::
          {{:ok, float} | {:error, :unknown_channel | :not_a_sensor}, t}
  def read_resistance(m, daq, channel) do
    address = {daq, channel}

    case ChannelMap.entry(m.config, address) do
      nil ->
        {{:error, :unknown_channel}, m}

      %{kind: :actuator} ->
        {{:error, :not_a_sensor}, m}

      %{kind: :gauge} = entry ->
        if open_circuit?(m, address) do
          {{:ok, m.config.overload}, m}
        else
          ohms = entry.ohms_at_zero + entry.ohms_per_newton * quantity(m, entry.signal)
          noisy(m, ohms, Map.get(entry, :noise, m.config.noise.gauge_ohms))
        end

      _other ->
        {{:ok, m.config.overload}, m}
    end
  end

  defp ideal_volts(m, %{kind: :switch, signal: signal}) do
    closed = switch(m, signal) and not Map.has_key?(m.faults, {:broken_switch, signal})
    if closed, do: m.config.switch.closed_volts * 1.0, else: m.config.switch.open_volts * 1.0
  end

  defp ideal_volts(m, %{kind: :pot} = entry),
    do: entry.volts_at_zero + entry.volts_per_unit * quantity(m, entry.signal)

  defp ideal_volts(_m, _gauge_or_spare), do: 0.0

  defp volts_noise(m, entry) do
    default =
      case entry.kind do
        :switch -> m.config.switch.noise
        :pot -> m.config.noise.pot_volts
        _ -> m.config.noise.spare_volts
      end

    Map.get(entry, :noise, default)
  end

  defp noisy(m, value, half_width) when half_width > 0 do
    {u, rand} = :rand.uniform_s(m.rand)
    {{:ok, value + half_width * (2 * u - 1)}, %{m | rand: rand}}
  end

  defp noisy(m, value, _none), do: {{:ok, value * 1.0}, m}

  defp open_circuit?(m, address), do: Map.has_key?(m.faults, {:sensor_open_circuit, address})

  @doc "Closes an actuator relay (`ROUT:CLOS`). Only `:actuator` channels have relays."
  @spec close_channel(t, daq, integer) :: {:ok | {:error, :unknown_channel | :not_an_actuator}, t}
  def close_channel(m, daq, channel), do: set_relay(m, {daq, channel}, true)

  @doc "Opens an actuator relay (`ROUT:OPEN`)."
  @spec open_channel(t, daq, integer) :: {:ok | {:error, :unknown_channel | :not_an_actuator}, t}
  def open_channel(m, daq, channel), do: set_relay(m, {daq, channel}, false)

  @doc "Opens every relay of one DAQ (its `*RST`)."
  @spec open_all(t, daq) :: t
  def open_all(m, daq) do
    settle(%{m | relays: MapSet.reject(m.relays, fn {d, _} -> d == daq end)})
  end

  @doc "Whether a relay is closed (`ROUT:CLOS?`) — the relay, not what the valve behind it did."
  @spec channel_closed?(t, daq, integer) ::
          {:ok, boolean} | {:error, :unknown_channel | :not_an_actuator}
  def channel_closed?(m, daq, channel) do
    address = {daq, channel}

    case ChannelMap.entry(m.config, address) do
      nil -> {:error, :unknown_channel}
      %{kind: :actuator} -> {:ok, MapSet.member?(m.relays, address)}
      _ -> {:error, :not_an_actuator}
    end
  end

  defp set_relay(m, address, closed?) do
    case ChannelMap.entry(m.config, address) do
      nil ->
        {{:error, :unknown_channel}, m}

      %{kind: :actuator} ->
        relays =
          if closed?,
            do: MapSet.put(m.relays, address),
            else: MapSet.delete(m.relays, address)

        {:ok, settle(%{m | relays: relays})}

      _ ->
        {{:error, :not_an_actuator}, m}
    end
  end

  ## Faults

  @doc """
  Injects a fault; see `Vws.Sim.Plant.inject_fault/3` for the kinds and their options.
  """
  @spec inject_fault(t, fault, keyword) :: {:ok, t} | {:error, :unknown_fault | :bad_options}
  def inject_fault(m, :stuck_valve, opts) do
    with {:ok, signal} <- named(opts, :actuator, :actuator) do
      {:ok, put_fault(m, {:stuck_valve, signal}, %{value: actuator?(m, signal)})}
    end
  end

  def inject_fault(m, :broken_switch, opts) do
    with {:ok, signal} <- named(opts, :switch, :switch),
         do: {:ok, put_fault(m, {:broken_switch, signal}, %{})}
  end

  def inject_fault(m, :no_part, opts) do
    case Keyword.get(opts, :where) do
      where when where in [:vise, :gripper] -> {:ok, put_fault(m, {:no_part, where}, %{})}
      _ -> {:error, :bad_options}
    end
  end

  def inject_fault(m, :weak_clamp, opts) do
    case {Keyword.get(opts, :where), Keyword.get(opts, :force_n)} do
      {where, force} when where in [:vise, :pallet] and is_number(force) and force >= 0 ->
        {:ok, put_fault(m, {:weak_clamp, where}, %{force_n: force * 1.0})}

      _ ->
        {:error, :bad_options}
    end
  end

  def inject_fault(m, :sensor_open_circuit, opts) do
    address =
      case {Keyword.get(opts, :signal), Keyword.get(opts, :channel)} do
        {nil, channel} -> {Keyword.get(opts, :daq, :daq1), channel}
        {signal, nil} -> ChannelMap.channel(m.config, signal)
        _ -> nil
      end

    case address && ChannelMap.entry(m.config, address) do
      %{kind: kind} when kind != :actuator ->
        {:ok, put_fault(m, {:sensor_open_circuit, address}, %{})}

      _ ->
        {:error, :bad_options}
    end
  end

  def inject_fault(_m, _fault, _opts), do: {:error, :unknown_fault}

  defp named(opts, key, kind) do
    signal = Keyword.get(opts, key)

    if signal in Map.fetch!(ChannelMap.signals(), kind),
      do: {:ok, signal},
      else: {:error, :bad_options}
  end

  defp put_fault(m, key, value), do: settle(%{m | faults: Map.put(m.faults, key, value)})

  @doc "Clears every fault of one kind, or all faults with `:all`."
  @spec clear_fault(t, fault | :all) :: t
  def clear_fault(m, :all), do: settle(%{m | faults: %{}})

  def clear_fault(m, kind) do
    settle(%{m | faults: Map.reject(m.faults, fn {{k, _}, _} -> k == kind end)})
  end

  ## The world around the plant

  @doc """
  Puts a part at `where` (`true` = a part of the configured width, or a width in mm) or takes
  it away (`false`). A part cannot go into vise jaws or gripper fingers narrower than it.
  """
  @spec set_part(t, where, boolean | number) :: {:ok, t} | {:error, :no_room | :bad_place}
  def set_part(m, where, false) when where in [:vise, :gripper, :tray1, :tray2],
    do: {:ok, settle(%{m | parts: %{m.parts | where => nil}})}

  def set_part(m, where, true), do: set_part(m, where, m.config.part_width_mm)

  def set_part(m, where, width)
      when where in [:vise, :gripper, :tray1, :tray2] and is_number(width) and width > 0 do
    room =
      case where do
        :vise -> m.vise.jaw_mm
        :gripper -> m.gripper.finger_mm
        _ -> :infinity
      end

    if room == :infinity or room >= width - @eps,
      do: {:ok, settle(%{m | parts: %{m.parts | where => width * 1.0}})},
      else: {:error, :no_room}
  end

  def set_part(_m, _where, _value), do: {:error, :bad_place}

  @doc """
  Tells the plant where the robot's gripper is: `%{volume: atom}` (`:safe`, `:table`, `:vise`,
  `:pallet`, `:tray1`, `:tray2`, …) and optionally `carrying: boolean` to put a part into the
  gripper (between its fingers, as if picked) or take it away, as a robot simulator may do.
  """
  @spec set_robot(t, map) :: t
  def set_robot(m, %{volume: volume} = robot) when is_atom(volume) do
    m = %{m | robot: volume}

    m =
      case Map.fetch(robot, :carrying) do
        {:ok, true} ->
          carry(m, m.parts.gripper || m.config.part_width_mm)

        {:ok, false} ->
          %{m | parts: %{m.parts | gripper: nil}}

        :error ->
          m
      end

    settle(m)
  end

  # The part is between the fingers, so they are at least as wide as it.
  defp carry(m, width) do
    finger = max(m.gripper.finger_mm, width)
    %{m | parts: %{m.parts | gripper: width}, gripper: %{m.gripper | finger_mm: finger}}
  end

  @doc """
  Starts (`true`) or ends (`false`) a machining cycle: the table leaves park while it runs and
  returns after. Starting one while the vise is still moving is a collision.
  """
  @spec set_cycle(t, boolean) :: t
  def set_cycle(%{cycle: cycle} = m, cycle), do: settle(m)

  def set_cycle(m, true) do
    m =
      if vise_moving?(m),
        do: record(m, :cycle_started_vise_not_released, %{vise: m.vise}),
        else: m

    settle(%{m | cycle: true})
  end

  def set_cycle(m, false), do: settle(%{m | cycle: false})

  @doc "Tool changer 1's fingers release (`true`) or hold their tool (`false`)."
  @spec set_changer1(t, boolean) :: t
  def set_changer1(m, released?) when is_boolean(released?),
    do: settle(%{m | changer1_released: released?})

  @doc "The material-handling system moves a tray; refused while its lock relay holds it."
  @spec move_tray(t, 1 | 2, :in | :out) :: {:ok, t} | {:error, :locked}
  def move_tray(m, tray, direction) when tray in [1, 2] and direction in [:in, :out] do
    lock = if tray == 1, do: :tray1_lock, else: :tray2_lock

    if actuator?(m, lock) do
      {:error, :locked}
    else
      target = if direction == :in, do: m.config.motion.tray_travel_mm * 1.0, else: 0.0
      {:ok, settle(put_in(m.trays[tray].target_mm, target))}
    end
  end

  ## Inspection

  @doc "The true physical state: positions in mm or degrees, forces in N, switches as booleans."
  @spec snapshot(t) :: map
  def snapshot(m) do
    %{
      time_s: m.t,
      vise: %{
        jaw_mm: m.vise.jaw_mm,
        force_n: m.vise.force_n,
        part_present: part(m, :vise) != nil,
        fully_open: switch(m, :vise_fully_open),
        moving: vise_moving?(m)
      },
      gripper: %{
        finger_mm: m.gripper.finger_mm,
        fully_open: switch(m, :gripper_fully_open),
        indexer_deg: m.gripper.indexer_deg,
        holding: part(m, :gripper) != nil
      },
      vacuum: %{on: switch(m, :vacuum_on)},
      trays:
        Map.new(m.trays, fn {n, tray} ->
          {n,
           %{
             mm: tray.mm,
             in_position: tray_in?(m, n),
             moving: tray_moving?(m, n),
             locked: actuator?(m, if(n == 1, do: :tray1_lock, else: :tray2_lock))
           }}
        end),
      table: %{mm: m.table_mm, parked: table_parked?(m), cycle: m.cycle},
      cycle_start_relay: actuator?(m, :cycle_start_relay),
      pallet:
        Map.merge(m.pallet, %{x_switch: switch(m, :pallet_x), y_switch: switch(m, :pallet_y)}),
      robot: %{volume: m.robot, carrying: m.parts.gripper != nil},
      parts: m.parts,
      relays: m.relays |> MapSet.to_list() |> Enum.sort(),
      faults: m.faults
    }
  end

  @doc "The collisions recorded so far, oldest first."
  @spec collisions(t) :: [collision]
  def collisions(m), do: Enum.reverse(m.collisions)
end
