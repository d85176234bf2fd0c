defmodule Vws.Peers.HydraulicControllerPeerTest do
  # The hydraulic controller in a node of its own (`:peer`, over its standard I/O: the test node
  # needs no distribution), reached by a workstation here over the HPIB only.
  use ExUnit.Case, async: true

  alias Vws.Test.HydraulicFloor

  setup do
    paths = Enum.flat_map(:code.get_path(), &[~c"-pa", &1])

    {:ok, peer, _node} =
      :peer.start_link(%{
        connection: :standard_io,
        name: :peer.random_name(~c"hydraulic"),
        args: paths ++ [~c"-logger", ~c"level", ~c"error"]
      })

    on_exit(fn -> if Process.alive?(peer), do: :peer.stop(peer) end)

    {:ok, _} = :peer.call(peer, Application, :ensure_all_started, [:vws], 30_000)
    :ok = :peer.call(peer, Logger, :configure, [[level: :error]])
    remote = :peer.call(peer, Vws.Test.RemoteHydraulic, :start, [[]], 30_000)
    %{peer: peer, remote: remote}
  end

  test "clamp and release on a controller in another node; the node gone is NO DATA", %{
    peer: peer,
    remote: remote
  } do
    %{peer: wc} = HydraulicFloor.workstation(remote)
    assert HydraulicFloor.await_pallet(wc, &(&1 =~ "PALLET")) == "PALLET NOT CLAMPED"

    assert HydraulicFloor.command(wc, 1, "CLAMP_PALLET") == "DONE"
    assert HydraulicFloor.pallet(wc) == "PALLET CLAMPED"
    assert %{force1_n: 5000.0} = :peer.call(peer, Vws.Sim.Plant, :snapshot, [remote.plant]).pallet

    :ok =
      :peer.call(peer, Vws.Sim.Plant, :inject_fault, [
        remote.plant,
        :weak_clamp,
        [where: :pallet, force_n: 1200]
      ])

    assert HydraulicFloor.command(wc, 2, "RELEASE_PALLET") == "DONE"

    assert HydraulicFloor.command(wc, 3, "CLAMP_PALLET") =~
             ~r/^ERROR CLAMP 1 FORCE \d+ N BELOW 4000 N$/

    :peer.stop(peer)

    assert HydraulicFloor.await_pallet(wc, &(&1 =~ "NO DATA")) =~
             ~r/^NO DATA \(HYDRAULIC CONTROLLER (NOT CONNECTED|CONNECTION LOST)\)$/
  end
end
