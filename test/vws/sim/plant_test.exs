defmodule Vws.Sim.PlantTest do
  use ExUnit.Case, async: true

  alias Vws.Sim.Plant

  doctest Vws.Sim.Plant

  # Conversions of priv/plant.exs, written out here so the tests read like a shop engineer
  # reading a voltmeter.
  @closed_v 5.0
  @switch_noise 0.02
  defp closed?(plant, ch), do: volts(plant, ch) > 2.5
  defp volts(plant, ch), do: ok(Plant.read_voltage(plant, ch))
  defp ohms(plant, ch), do: ok(Plant.read_resistance(plant, ch))
  defp vise_jaw_mm(plant), do: (volts(plant, 103) - 0.5) / 0.05
  defp finger_mm(plant), do: (volts(plant, 108) - 0.2) / 0.1
  defp vise_force_n(plant), do: (ohms(plant, 117) - 350.0) / 0.01
  defp clamp_force_n(plant, ch), do: (ohms(plant, {:daq2, ch}) - 350.0) / 0.002

  defp ok({:ok, value}), do: value

  # Polls until `check` returns a truthy value; the plant advances on every call, so at
  # time_scale 1000 a few real milliseconds are seconds of plant time. Generous bound.
  defp eventually(check, timeout_ms \\ 5_000) do
    deadline = System.monotonic_time(:millisecond) + timeout_ms
    poll(check, deadline)
  end

  defp poll(check, deadline) do
    if value = check.() do
      value
    else
      if System.monotonic_time(:millisecond) > deadline, do: flunk("condition never held")
      Process.sleep(2)
      poll(check, deadline)
    end
  end

  defp start(opts \\ []) do
    opts = Keyword.merge([time_scale: 1000, seed: 42], opts)
    start_supervised!({Plant, opts}, id: make_ref())
  end

  describe "vise" do
    test "closing on a part stops at its width, builds the clamp force, shows part present" do
      plant = start()
      :ok = Plant.set_part(plant, :vise, true)
      assert closed?(plant, 101)
      :ok = Plant.close_channel(plant, 206)

      eventually(fn -> vise_force_n(plant) > 1990 end)
      assert_in_delta vise_jaw_mm(plant), 50.0, 0.2
      assert closed?(plant, 101)
      refute closed?(plant, 102)
      assert_in_delta vise_force_n(plant), 2000.0, 10.0

      :ok = Plant.open_channel(plant, 206)
      :ok = Plant.close_channel(plant, 205)
      eventually(fn -> closed?(plant, 102) end)
      assert_in_delta vise_force_n(plant), 0.0, 10.0
      assert_in_delta vise_jaw_mm(plant), 150.0, 0.2
    end

    test "closing empty closes fully with no part present and no force" do
      plant = start()
      :ok = Plant.close_channel(plant, 206)
      eventually(fn -> vise_jaw_mm(plant) < 0.2 end)
      refute closed?(plant, 101)
      assert_in_delta vise_force_n(plant), 0.0, 10.0
    end

    test "a stroke takes simulated time: 1x is still moving when 1000x has finished" do
      slow = start(time_scale: 1)
      fast = start(time_scale: 1000)
      :ok = Plant.close_channel(slow, 206)
      :ok = Plant.close_channel(fast, 206)
      eventually(fn -> Plant.snapshot(fast).vise.jaw_mm == 0.0 end)
      assert Plant.snapshot(slow).vise.jaw_mm > 0.0
    end
  end

  describe "gripper, indexer, vacuum, table, pallet" do
    test "the gripper closing on nothing closes its fingers on themselves" do
      plant = start()
      assert closed?(plant, 107)
      :ok = Plant.close_channel(plant, 202)
      eventually(fn -> finger_mm(plant) < 0.1 end)
      refute closed?(plant, 107)
    end

    test "the indexer goes to (bit1 * 2 + bit0) * 90 degrees; the vacuum switch closes" do
      plant = start()
      assert closed?(plant, 109)
      :ok = Plant.close_channel(plant, 203)
      :ok = Plant.close_channel(plant, 204)
      :ok = Plant.close_channel(plant, 207)
      eventually(fn -> closed?(plant, 112) and closed?(plant, 113) end)
      refute closed?(plant, 109) or closed?(plant, 110) or closed?(plant, 111)
      assert Plant.snapshot(plant).gripper.indexer_deg == 270.0
    end

    test "a cycle takes the table out of park and brings it back" do
      plant = start()
      assert closed?(plant, 104)
      :ok = Plant.set_cycle(plant, true)
      eventually(fn -> not closed?(plant, 104) end)
      :ok = Plant.set_cycle(plant, false)
      eventually(fn -> closed?(plant, 104) end)
    end

    test "the pallet: rams close the X/Y switches, swing clamps build their force, release lets go" do
      plant = start()
      refute closed?(plant, {:daq2, 101}) or closed?(plant, {:daq2, 102})
      :ok = Plant.close_channel(plant, {:daq2, 201})
      :ok = Plant.close_channel(plant, {:daq2, 202})
      eventually(fn -> closed?(plant, {:daq2, 101}) and closed?(plant, {:daq2, 102}) end)
      :ok = Plant.close_channel(plant, {:daq2, 203})
      :ok = Plant.close_channel(plant, {:daq2, 204})
      eventually(fn -> clamp_force_n(plant, 103) > 4950 and clamp_force_n(plant, 104) > 4950 end)

      :ok = Plant.open_all(plant, :daq2)
      eventually(fn -> not closed?(plant, {:daq2, 101}) end)
      assert_in_delta clamp_force_n(plant, 103), 0.0, 50.0
      assert Plant.snapshot(plant).relays == []
    end
  end

  describe "trays" do
    test "a tray move is refused while its lock relay is closed" do
      plant = start()
      :ok = Plant.close_channel(plant, 208)
      assert closed?(plant, 114)
      assert Plant.move_tray(plant, 1, :out) == {:error, :locked}
      assert closed?(plant, 105)
      assert :ok = Plant.move_tray(plant, 2, :out)

      :ok = Plant.open_channel(plant, 208)
      assert :ok = Plant.move_tray(plant, 1, :out)
      eventually(fn -> not closed?(plant, 105) and not closed?(plant, 106) end)
      assert :ok = Plant.move_tray(plant, 1, :in)
      eventually(fn -> closed?(plant, 105) end)
    end
  end

  describe "faults, each with its own symptom" do
    test "stuck valve: the relay closes, the vise does not move; cleared, it does" do
      plant = start()
      :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vise_close_valve)
      :ok = Plant.close_channel(plant, 206)
      :ok = Plant.advance(plant, 10.0)
      assert Plant.channel_closed?(plant, 206) == {:ok, true}
      assert closed?(plant, 102)
      assert_in_delta vise_jaw_mm(plant), 150.0, 0.2

      :ok = Plant.clear_fault(plant, :stuck_valve)
      eventually(fn -> vise_jaw_mm(plant) < 0.2 end)
    end

    test "stuck valve held energised: opening the relay does not release" do
      plant = start()
      :ok = Plant.close_channel(plant, 207)
      eventually(fn -> closed?(plant, 113) end)
      :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vacuum_motor)
      :ok = Plant.open_channel(plant, 207)
      :ok = Plant.advance(plant, 10.0)
      assert closed?(plant, 113)
    end

    test "broken switch: reads open although the table is parked" do
      plant = start()
      :ok = Plant.inject_fault(plant, :broken_switch, switch: :table_park)
      assert Plant.snapshot(plant).table.parked
      assert_in_delta volts(plant, 104), 0.0, @switch_noise
      assert closed?(plant, 105)
      :ok = Plant.clear_fault(plant, :broken_switch)
      assert_in_delta volts(plant, 104), @closed_v, @switch_noise
    end

    test "no part in the vise: the jaws close on nothing, no part present, no force" do
      plant = start()
      :ok = Plant.set_part(plant, :vise, true)
      :ok = Plant.inject_fault(plant, :no_part, where: :vise)
      :ok = Plant.close_channel(plant, 206)
      eventually(fn -> vise_jaw_mm(plant) < 0.2 end)
      refute closed?(plant, 101)
      assert_in_delta vise_force_n(plant), 0.0, 10.0
    end

    test "no part in the gripper: the fingers close on nothing where a part should be" do
      plant = start()
      :ok = Plant.set_part(plant, :tray1, true)
      :ok = Plant.set_robot(plant, %{volume: :tray1})
      :ok = Plant.inject_fault(plant, :no_part, where: :gripper)
      :ok = Plant.close_channel(plant, 202)
      eventually(fn -> finger_mm(plant) < 0.1 end)
      assert Plant.snapshot(plant).parts.tray1 == 50.0
    end

    test "weak clamp: the vise force stops at the given value, the part is still there" do
      plant = start()
      :ok = Plant.inject_fault(plant, :weak_clamp, where: :vise, force_n: 500)
      :ok = Plant.set_part(plant, :vise, true)
      :ok = Plant.close_channel(plant, 206)
      eventually(fn -> vise_force_n(plant) > 490 end)
      :ok = Plant.advance(plant, 10.0)
      assert_in_delta vise_force_n(plant), 500.0, 10.0
      assert closed?(plant, 101)
      assert_in_delta vise_jaw_mm(plant), 50.0, 0.2
    end

    test "weak clamp on the pallet: both swing clamps stop at the given force" do
      plant = start()
      :ok = Plant.inject_fault(plant, :weak_clamp, where: :pallet, force_n: 1200)
      :ok = Plant.close_channel(plant, {:daq2, 203})
      :ok = Plant.close_channel(plant, {:daq2, 204})
      eventually(fn -> clamp_force_n(plant, 103) > 1150 and clamp_force_n(plant, 104) > 1150 end)
      :ok = Plant.advance(plant, 10.0)
      assert_in_delta clamp_force_n(plant, 103), 1200.0, 50.0
    end

    test "sensor open circuit: the channel reads overload, its neighbours do not" do
      plant = start()
      :ok = Plant.inject_fault(plant, :sensor_open_circuit, channel: 103)
      :ok = Plant.inject_fault(plant, :sensor_open_circuit, signal: :vise_force_n)
      assert Plant.read_voltage(plant, 103) == {:ok, 9.9e37}
      assert Plant.read_resistance(plant, 117) == {:ok, 9.9e37}
      assert volts(plant, 104) < 9.0
      :ok = Plant.clear_fault(plant, :all)
      assert_in_delta vise_jaw_mm(plant), 150.0, 0.2
    end

    test "bad fault requests are refused" do
      plant = start()
      assert Plant.inject_fault(plant, :gremlins, []) == {:error, :unknown_fault}

      assert Plant.inject_fault(plant, :stuck_valve, actuator: :table_park) ==
               {:error, :bad_options}

      assert Plant.inject_fault(plant, :broken_switch, switch: :vise_close_valve) ==
               {:error, :bad_options}

      assert Plant.inject_fault(plant, :weak_clamp, where: :vise) == {:error, :bad_options}

      assert Plant.inject_fault(plant, :sensor_open_circuit, channel: 201) ==
               {:error, :bad_options}

      assert Plant.snapshot(plant).faults == %{}
    end
  end

  describe "sensor noise" do
    @at_rest [
      {101, 0.0, 0.02},
      {102, 5.0, 0.02},
      {103, 8.0, 0.005},
      {104, 5.0, 0.02},
      {108, 8.2, 0.005},
      {110, 0.0, 0.02},
      # tool changer 1 released at rest
      {116, 5.0, 0.02}
    ]

    test "stays within the configured half-widths, and is there" do
      plant = start(time_scale: 0)

      for {ch, ideal, half} <- @at_rest do
        readings = for _ <- 1..200, do: volts(plant, ch)
        assert Enum.all?(readings, &(abs(&1 - ideal) <= half)), "channel #{ch}"
        assert Enum.max(readings) - Enum.min(readings) > half / 2, "channel #{ch} has no noise"
      end

      ohms = for _ <- 1..200, do: ohms(plant, 117)
      assert Enum.all?(ohms, &(abs(&1 - 350.0) <= 0.05))
    end

    test "a channel's own noise overrides the default" do
      pot = %{
        kind: :pot,
        signal: :vise_jaw_mm,
        volts_at_zero: 0.5,
        volts_per_unit: 0.05,
        noise: 0.1
      }

      plant = start(time_scale: 0, config: %{daq1: %{103 => pot}})
      readings = for _ <- 1..200, do: volts(plant, 103)
      assert Enum.all?(readings, &(abs(&1 - 8.0) <= 0.1))
      assert Enum.max(readings) - Enum.min(readings) > 0.05
    end

    test "is the same for the same seed" do
      read = fn plant -> for _ <- 1..20, do: volts(plant, 103) end
      a = read.(start(time_scale: 0, seed: 5))
      assert read.(start(time_scale: 0, seed: 5)) == a
      refute read.(start(time_scale: 0, seed: 6)) == a
    end
  end

  describe "channels" do
    test "errors for channels that are not there or not of that kind" do
      plant = start()
      assert Plant.read_voltage(plant, 199) == {:error, :unknown_channel}
      assert Plant.read_voltage(plant, 201) == {:error, :not_a_sensor}
      assert Plant.close_channel(plant, 101) == {:error, :not_an_actuator}
      assert Plant.channel_closed?(plant, {:daq2, 299}) == {:error, :unknown_channel}
      assert Plant.read_resistance(plant, 101) == {:ok, 9.9e37}
    end

    test "several named plants run side by side" do
      start_supervised!({Plant, name: :plant_a, time_scale: 0})
      start_supervised!({Plant, name: :plant_b, time_scale: 0})
      :ok = Plant.close_channel(:plant_a, 210)
      assert Plant.channel_closed?(:plant_a, 210) == {:ok, true}
      assert Plant.channel_closed?(:plant_b, 210) == {:ok, false}
      assert Plant.snapshot(:plant_a).cycle_start_relay
    end
  end

  describe "collisions" do
    defp kinds(plant), do: plant |> Plant.collisions() |> Enum.map(& &1.kind)

    defp swap(plant, off, on) do
      :ok = Plant.open_channel(plant, off)
      :ok = Plant.close_channel(plant, on)
    end

    test "none in a normal load, machine, unload sequence" do
      p = start(time_scale: 0)
      :ok = Plant.set_part(p, :tray1, true)

      # pick the blank from tray 1 with the tray locked
      :ok = Plant.close_channel(p, 208)
      :ok = Plant.set_robot(p, %{volume: :tray1})
      :ok = Plant.close_channel(p, 202)
      :ok = Plant.advance(p, 1.0)
      assert Plant.snapshot(p).gripper.holding
      :ok = Plant.set_robot(p, %{volume: :safe})
      :ok = Plant.open_channel(p, 208)

      # load the vise: it takes the part from the gripper
      :ok = Plant.set_robot(p, %{volume: :vise})
      :ok = Plant.close_channel(p, 206)
      :ok = Plant.advance(p, 2.0)
      swap(p, 202, 201)
      :ok = Plant.advance(p, 1.0)
      :ok = Plant.set_robot(p, %{volume: :safe})
      assert %{part_present: true, force_n: 2000.0} = Plant.snapshot(p).vise
      :ok = Plant.open_channel(p, 206)

      # machine
      :ok = Plant.close_channel(p, 210)
      :ok = Plant.set_cycle(p, true)
      :ok = Plant.open_channel(p, 210)
      :ok = Plant.advance(p, 5.0)
      :ok = Plant.set_cycle(p, false)
      :ok = Plant.advance(p, 3.0)

      # unload: grip, open the vise (the part comes with the fingers), put it in tray 2
      :ok = Plant.set_robot(p, %{volume: :vise})
      swap(p, 201, 202)
      :ok = Plant.advance(p, 1.0)
      :ok = Plant.close_channel(p, 205)
      :ok = Plant.advance(p, 2.0)
      :ok = Plant.open_channel(p, 205)
      assert Plant.snapshot(p).gripper.holding
      :ok = Plant.set_robot(p, %{volume: :safe})
      :ok = Plant.close_channel(p, 209)
      :ok = Plant.set_robot(p, %{volume: :tray2})
      swap(p, 202, 201)
      :ok = Plant.advance(p, 1.0)
      :ok = Plant.set_robot(p, %{volume: :safe})
      :ok = Plant.open_channel(p, 209)
      :ok = Plant.move_tray(p, 2, :out)
      :ok = Plant.advance(p, 10.0)

      assert Plant.collisions(p) == []
      assert Plant.snapshot(p).parts == %{vise: nil, gripper: nil, tray1: nil, tray2: 50.0}
    end

    test "robot in the table volume while a cycle runs or the table is out of park" do
      p = start(time_scale: 0)
      :ok = Plant.set_cycle(p, true)
      :ok = Plant.set_robot(p, %{volume: :table})
      assert kinds(p) == [:robot_in_table_volume]
      # one record per episode
      :ok = Plant.advance(p, 5.0)
      assert kinds(p) == [:robot_in_table_volume]

      :ok = Plant.set_robot(p, %{volume: :safe})
      :ok = Plant.set_cycle(p, false)
      :ok = Plant.advance(p, 0.5)
      :ok = Plant.set_robot(p, %{volume: :vise})
      assert [_, %{kind: :robot_in_table_volume, detail: %{volume: :vise}}] = Plant.collisions(p)
    end

    test "a tray moved while the robot is in its volume" do
      p = start(time_scale: 0)
      :ok = Plant.set_robot(p, %{volume: :tray2})
      :ok = Plant.move_tray(p, 1, :out)
      assert kinds(p) == []
      :ok = Plant.move_tray(p, 2, :out)
      assert [%{kind: :tray_moved_with_robot, detail: %{tray: 2}}] = Plant.collisions(p)
    end

    test "the vise opened during a cycle" do
      p = start(time_scale: 0)
      :ok = Plant.set_part(p, :vise, true)
      :ok = Plant.close_channel(p, 206)
      :ok = Plant.advance(p, 2.0)
      :ok = Plant.set_cycle(p, true)
      swap(p, 206, 205)
      assert kinds(p) == [:vise_opened_during_cycle]
    end

    test "a cycle started with the vise not released" do
      p = start(time_scale: 0)
      :ok = Plant.set_part(p, :vise, true)
      :ok = Plant.close_channel(p, 206)
      :ok = Plant.advance(p, 0.5)
      :ok = Plant.set_cycle(p, true)
      assert [%{kind: :cycle_started_vise_not_released, at_s: 0.5}] = Plant.collisions(p)
    end

    test "a part dropped where nothing can hold it" do
      p = start(time_scale: 0)
      :ok = Plant.set_robot(p, %{volume: :safe, carrying: true})
      :ok = Plant.close_channel(p, 201)
      :ok = Plant.advance(p, 1.0)
      assert kinds(p) == [:part_dropped]
      refute Plant.snapshot(p).gripper.holding
    end
  end
end

defmodule Vws.Sim.PlantWritesTest do
  # issue 15: one account of the relay writes serves Plant.writes/1 and the telemetry
  use ExUnit.Case, async: true

  alias Vws.Sim.Plant

  test "Plant.writes/1 and the [:vws, :sim, :plant, :actuator] events count the same writes" do
    ws = "plant-writes-#{System.unique_integer([:positive])}"
    plant = start_supervised!({Plant, time_scale: 0, name: Vws.Names.via(ws, :plant)})
    test = self()
    handler = {__MODULE__, ws}

    :ok =
      Vws.Telemetry.attach(
        handler,
        [:vws, :sim, :plant, :actuator],
        fn _, %{count: n}, m, _ ->
          if m.workstation == ws, do: send(test, {:write, {m.daq, m.channel}, m.action, n})
        end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(handler) end)

    :ok = Plant.close_channel(plant, 207)
    :ok = Plant.close_channel(plant, 207)
    :ok = Plant.open_channel(plant, {:daq2, 201})
    # an *RST opens every relay of the DAQ: each is a write, in both accounts
    :ok = Plant.open_all(plant, :daq1)
    # not a relay: no write in either
    assert {:error, _} = Plant.close_channel(plant, 101)

    writes = Plant.writes(plant)
    events = collect(%{})
    assert events == writes
    assert writes[{:daq1, 207}] == %{close: 2, open: 1}
    assert writes[{:daq2, 201}] == %{close: 0, open: 1}
    assert map_size(writes) == length(Vws.Links.DAQ.slot(Vws.Links.DAQ.new())) + 1
  end

  defp collect(acc) do
    receive do
      {:write, address, action, n} ->
        acc
        |> Map.update(
          address,
          Map.put(%{close: 0, open: 0}, action, n),
          &Map.update!(&1, action, fn c -> c + n end)
        )
        |> collect()
    after
      200 -> acc
    end
  end
end
