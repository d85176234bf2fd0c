defmodule Vws.Sim.Plant.ModelTest do
  use ExUnit.Case, async: true

  alias Vws.Links.DAQ.ChannelMap
  alias Vws.Sim.Plant.Model

  doctest Model

  @config ChannelMap.load()

  defp new, do: Model.new(@config, 1)

  defp close(m, ch, daq \\ :daq1) do
    {:ok, m} = Model.close_channel(m, daq, ch)
    m
  end

  defp open(m, ch, daq \\ :daq1) do
    {:ok, m} = Model.open_channel(m, daq, ch)
    m
  end

  defp part(m, where, value) do
    {:ok, m} = Model.set_part(m, where, value)
    m
  end

  test "motion takes the configured time: a vise stroke is 1.5 s, the force rises in 0.3 s" do
    m = new() |> part(:vise, true) |> close(206)
    assert Model.snapshot(Model.advance(m, 0.75)).vise.jaw_mm == 75.0

    # 100 mm of travel to the 50 mm part takes 1.0 s; then 0.15 s of force rise is half of 2000 N
    m = Model.advance(m, 1.15)
    assert_in_delta Model.snapshot(m).vise.force_n, 1000.0, 1.0e-6
    assert Model.snapshot(m).vise.moving
    m = Model.advance(m, 1.0)
    assert %{jaw_mm: 50.0, force_n: 2000.0, moving: false} = Model.snapshot(m).vise
  end

  test "neither valve holds jaws and force; both valves hold too" do
    m = new() |> part(:vise, true) |> close(206) |> Model.advance(3.0) |> open(206)
    assert %{jaw_mm: 50.0, force_n: 2000.0} = Model.snapshot(Model.advance(m, 5.0)).vise
    m = m |> close(205) |> close(206) |> Model.advance(5.0)
    assert %{jaw_mm: 50.0, force_n: 2000.0} = Model.snapshot(m).vise
  end

  test "a part does not fit in closed jaws or fingers" do
    m = new() |> close(206) |> Model.advance(2.0)
    assert Model.set_part(m, :vise, true) == {:error, :no_room}
    assert Model.set_part(m, :gripper, 90) == {:error, :no_room}
    assert Model.set_part(m, :tray1, 200) |> elem(0) == :ok
    assert Model.set_part(m, :table, true) == {:error, :bad_place}
  end

  test "parts travel tray 1 -> gripper -> vise -> gripper -> tray 2" do
    m = new() |> part(:tray1, 40)
    m = Model.set_robot(m, %{volume: :tray1}) |> close(202) |> Model.advance(1.0)
    assert %{gripper: 40.0, tray1: nil} = Model.snapshot(m).parts
    assert Model.snapshot(m).gripper.finger_mm == 40.0

    # the vise closes on the part the gripper holds and takes it
    m = Model.set_robot(m, %{volume: :vise}) |> close(206) |> Model.advance(2.0)
    assert %{vise: 40.0, gripper: nil} = Model.snapshot(m).parts
    assert %{jaw_mm: 40.0, force_n: 2000.0} = Model.snapshot(m).vise

    # fingers still on the clamped part; opening the vise hands it to them
    m = m |> open(206) |> close(205) |> Model.advance(2.0)
    assert %{vise: nil, gripper: 40.0} = Model.snapshot(m).parts

    m = Model.set_robot(m, %{volume: :tray2}) |> open(202) |> close(201) |> Model.advance(1.0)
    assert Model.snapshot(m).parts == %{vise: nil, gripper: nil, tray1: nil, tray2: 40.0}
    assert Model.collisions(m) == []
  end

  test "a tray that is out of position holds no part the gripper can reach" do
    m = new() |> part(:tray1, true)
    {:ok, m} = Model.move_tray(m, 1, :out)
    m = Model.advance(m, 10.0) |> Model.set_robot(%{volume: :tray1}) |> close(202)
    m = Model.advance(m, 1.0)
    assert Model.snapshot(m).gripper.finger_mm == 0.0
    assert Model.snapshot(m).parts.tray1 == 50.0
  end

  test "sensor readings follow the channel map's conversions exactly when noise is off" do
    config =
      ChannelMap.load(%{
        switch: %{noise: 0},
        noise: %{pot_volts: 0, gauge_ohms: 0, spare_volts: 0}
      })

    m = Model.new(config, 1) |> part(:vise, true) |> close(206) |> Model.advance(3.0)
    {{:ok, volts}, m} = Model.read_voltage(m, :daq1, 103)
    assert_in_delta volts, 0.5 + 0.05 * 50, 1.0e-9
    {{:ok, ohms}, m} = Model.read_resistance(m, :daq1, 117)
    assert_in_delta ohms, 350.0 + 0.01 * 2000, 1.0e-9
    {{:ok, volts}, _m} = Model.read_voltage(m, :daq1, 101)
    assert volts == 5.0
  end

  test "the robot entering a moving tray's volume is a collision, once" do
    {:ok, m} = Model.move_tray(new(), 1, :out)
    m = Model.advance(m, 1.0) |> Model.set_robot(%{volume: :tray1}) |> Model.advance(1.0)
    assert [%{kind: :tray_moved_with_robot, at_s: 1.0, detail: %{tray: 1}}] = Model.collisions(m)
  end
end
