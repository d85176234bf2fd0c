defmodule Vws.Ops.InspectFloorTest do
  # The views on the configuration people run (`mix vws.serve`, `mix vws.demo`): a workstation
  # on the whole simulated floor — DAQ #1 and the hydraulic controller on the HPIB, the GE-2000
  # on DNC, the VAL II on DDCMP. Every poll of the dashboard and every iex view used to crash on
  # the HPIB devices (Vws.Links.HPIB.info/1 was asked with a pid), leaving "workstations": [].
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO

  alias Vws.Ops.Inspect
  alias Vws.Sim.Floor

  setup do
    ws = "floor-inspect-#{System.unique_integer([:positive])}"

    start_supervised!(
      {Floor,
       workstation: ws,
       time_scale: 100,
       hydraulic: {Vws.Peers.HydraulicController, []},
       ge2000: true,
       robot: true},
      id: make_ref()
    )

    :ok = Vws.Peers.HydraulicController.await_ready(Floor.hydraulic_controller(ws), 10_000)
    # stale only after 10 s: a loaded machine (the whole suite on two cores) must not blank the
    # readings this test reads; staleness itself is tested in vws_status_test.exs
    Vws.Test.Workstation.start(
      id: ws,
      devices: Floor.devices(ws),
      partitions: [vws_status: [stale_after_ms: 10_000]]
    )

    # DAQ #1 answered: the readings are there to be shown
    assert Vws.Test.Eventually.eventually(fn ->
             match?({:ok, _}, Vws.Partitions.VwsStatus.readings(ws))
           end)

    %{ws: ws}
  end

  test "links, overview and the dashboard's state show every device link of the floor", %{ws: ws} do
    rows = Inspect.link_rows(ws)
    names = Enum.map(rows, & &1.name)

    for name <- [
          "DAQ #1 (HPIB 9)",
          "HYDRAULIC CONTROLLER (HPIB 8)",
          "GE-2000 (DNC)",
          "VAL II (DDCMP)"
        ] do
      assert name in names, "#{name} missing from #{inspect(names)}"
    end

    daq1 = Enum.find(rows, &(&1.name == "DAQ #1 (HPIB 9)"))
    assert %{info: %{device: "DAQ #1", address: 9, requests: requests}} = daq1
    assert requests > 0
    refute Enum.any?(rows, &(&1.state in [:unreadable, :not_answering]))

    # the iex views print, they do not crash the shell
    out = capture_io(fn -> Inspect.overview(ws) end)
    assert out =~ ~r/DAQ #1 \(HPIB 9\) +#PID<[\d.]+> +(ready|busy)/
    assert out =~ "GE-2000 (DNC)"
    assert out =~ ~r/SENSORS +\S+ +POLL \d+: GRIPPER FINGER GAP [\d.]+ MM/
    refute out =~ "%Vws."
    assert capture_io(fn -> :ok = Inspect.links(ws) end) =~ "HYDRAULIC CONTROLLER (HPIB 8)"

    # the dashboard's state has the workstation, its links, and the numbers from the sensors
    state = Vws.Ops.Web.State.build()
    [me] = for w <- state.workstations, w.id == ws, do: w
    assert "DAQ #1 (HPIB 9)" in Enum.map(me.links, & &1.id)

    assert %{value: jaw, unit: "mm"} =
             Enum.find(me.sensors.quantities, &(&1.name == "vise jaw width"))

    assert is_float(jaw)

    # the floor's hydraulic controller and its own link to DAQ #2 (equipment of this node)
    equipment = Enum.find(state.equipment, &(&1.name =~ ws))
    assert %{state: "ready", links: [%{id: "DAQ #2 (HPIB 9)", state: "ready"}]} = equipment
  end
end
