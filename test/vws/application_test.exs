defmodule Vws.ApplicationTest do
  use ExUnit.Case, async: true

  alias Vws.Test.WCPeer

  # A release with VWS_DAQ2 (README's table): the hydraulic controller runs in the node, on
  # DAQ #2, and the workstation reaches it — VWS_DAQ2 made the configured workstation crash
  # ("unknown device :daq2"), leaving a node without one.
  test "the configured workstation with devices: [daq2: …] runs the hydraulic controller on DAQ #2" do
    ws = "app-daq2-#{System.unique_integer([:positive])}"
    start_supervised!({Vws.Sim.Floor, workstation: ws, time_scale: 100, daq1: false})
    daq2 = Vws.Sim.Floor.daq2_endpoint(ws)

    on_exit(fn ->
      Vws.CEC.Workstation.stop(ws)

      for {_, pid, _, _} <- DynamicSupervisor.which_children(Vws.EquipmentSupervisor),
          Registry.keys(Vws.Registry, pid) == [{{:hydraulic_controller, {:configured, ws}}, :sup}],
          do: DynamicSupervisor.terminate_child(Vws.EquipmentSupervisor, pid)
    end)

    assert {:ok, _} =
             Vws.Application.start_configured(
               id: ws,
               wc: "loopback:#{ws}",
               devices: [daq2: daq2]
             )

    assert Vws.Peers.HydraulicController.status({:configured, ws}) != nil
    {:ok, peer} = WCPeer.connect("loopback:#{ws}")

    assert WCPeer.await_status(
             peer,
             1,
             "PALLET",
             &(not String.starts_with?(&1, "NO DATA")),
             10_000
           ) =~
             ~r/PALLET/
  end
end
