defmodule Vws.Sim.FloorTest do
  use ExUnit.Case, async: true

  doctest Vws.Sim.Floor

  test "the demo's shop floor: a workstation wired to the floor polls the plant" do
    ws = "floor-#{System.unique_integer([:positive])}"

    {:ok,
     %{
       name: "plant + DAQ #1 + DAQ #2 + hydraulic controller, GE-2000, VAL II, material handling",
       links: links,
       partitions: partitions
     }} = Vws.Ops.Demo.shop_floor(workstation: ws, time_scale: 100)

    start_supervised!(
      {Vws.CEC.Workstation, id: ws, wc: nil, links: links, partitions: partitions}
    )

    assert Vws.Test.Eventually.eventually(fn ->
             Vws.CEC.SunComm.Status.answer(ws, "VACUUM") == "VACUUM IS OFF"
           end)

    # through VWS_STATUS, DAQ #1's one writer: closed on the plant behind its back, the relay was
    # opened again when VWS_STATUS's start-up release of the buttons, read before and confirmed
    # after, found it "not as commanded" and set the slot right (VACUUM IS OFF for 30 s, twice in
    # full suites)
    :ok = Vws.Partitions.VwsStatus.actuate(ws, vacuum_motor: :close)

    assert Vws.Test.Eventually.eventually(
             fn -> Vws.CEC.SunComm.Status.answer(ws, "VACUUM") == "VACUUM IS ON" end,
             30_000
           ),
           "VACUUM answers #{inspect(Vws.CEC.SunComm.Status.answer(ws, "VACUUM"))}; VWS_STATUS: " <>
             inspect(Vws.Partitions.VwsStatus.stats(ws))

    # the hydraulic controller on DAQ #2 keeps the PALLET status
    assert Vws.Test.Eventually.eventually(fn ->
             Vws.CEC.SunComm.Status.answer(ws, "PALLET") == "PALLET NOT CLAMPED"
           end)

    Enum.each(
      201..204,
      &(:ok = Vws.Sim.Plant.close_channel(Vws.Sim.Floor.plant(ws), {:daq2, &1}))
    )

    assert Vws.Test.Eventually.eventually(fn ->
             Vws.CEC.SunComm.Status.answer(ws, "PALLET") == "PALLET CLAMPED"
           end)
  end

  test "without DAQ #1, or with the hydraulic controller, as asked" do
    ws = "floor-#{System.unique_integer([:positive])}"

    start_supervised!(
      {Vws.Sim.Floor,
       workstation: ws, daq1: false, hydraulic: {Vws.Peers.HydraulicController, []}}
    )

    assert Vws.Sim.Floor.daq2_endpoint(ws) =~ "tcp://"
    controller = Vws.Sim.Floor.hydraulic_controller(ws)
    assert Vws.Peers.HydraulicController.await_ready(controller, 5_000) == :ok
    assert Vws.Peers.HydraulicController.status(controller) == :done
    assert Vws.Sim.Floor.hydraulic_endpoint(ws) =~ "tcp://"
    assert Vws.Sim.Floor.daq1(ws) |> GenServer.whereis() == nil
  end

  test "the wires: the cycle-start relay starts the GE-2000, whose cycle moves the table" do
    ws = "floor-#{System.unique_integer([:positive])}"

    start_supervised!(
      {Vws.Sim.Floor,
       workstation: ws,
       time_scale: 1000,
       ge2000: [cycle_time: 200, programs: %{"000100.PRO" => "O100\nM30\n"}],
       robot: true}
    )

    plant = Vws.Sim.Floor.plant(ws)
    ge = Vws.Sim.Floor.ge2000(ws)

    assert [daq1: "tcp://" <> _, ge2000: "tcp://" <> _, robot: "tcp://" <> _] =
             Vws.Sim.Floor.devices(ws)

    # no program selected: the press is refused by the machine (alarm 4), the table stays
    :ok = Vws.Sim.Plant.close_channel(plant, 210)
    :ok = Vws.Sim.Plant.open_channel(plant, 210)
    assert Vws.Test.Eventually.eventually(fn -> Vws.Sim.GE2000.state(ge).alarm == 4 end)

    :sys.replace_state(ge, &%{&1 | selected: "000100"})
    :ok = Vws.Sim.Plant.close_channel(plant, 210)
    assert Vws.Test.Eventually.eventually(fn -> Vws.Sim.GE2000.state(ge).state == :active end)
    assert Vws.Sim.Plant.snapshot(plant).table.cycle
    :ok = Vws.Sim.Plant.open_channel(plant, 210)
    assert Vws.Test.Eventually.eventually(fn -> Vws.Sim.Plant.snapshot(plant).table.parked end)
    assert Vws.Sim.GE2000.state(ge).cycles == 1
    assert Vws.Sim.Plant.collisions(plant) == []
  end
end
