defmodule Vws.CEC.CellDistributedTest do
  # A cell of three `:peer` nodes, a workstation on each, driven by WC clients on this node.
  # Not async: this node becomes distributed for the module's duration.
  use ExUnit.Case, async: false

  @moduletag :distributed
  @moduletag timeout: 60_000

  alias Vws.CEC.Cell
  alias Vws.Test.CellPeers
  alias Vws.Peers.WC.{Client, Runner, Script}
  import Vws.Test.Eventually

  @peers 3

  setup_all do
    started_distribution? = CellPeers.ensure_distributed!()
    tag = System.unique_integer([:positive])

    peers =
      1..@peers
      |> Enum.map(fn i -> Task.async(fn -> start_peer(i, tag) end) end)
      |> Task.await_many(30_000)

    CellPeers.mesh!(Enum.map(peers, & &1.node))

    on_exit(fn ->
      for %{peer: peer} <- peers, do: CellPeers.stop(peer)
      if started_distribution?, do: :net_kernel.stop()
    end)

    %{peers: peers}
  end

  defp start_peer(i, tag) do
    %{node: node} = peer = CellPeers.start!("vws_cell_#{tag}_#{i}")
    id = "cell-#{tag}-#{i}"

    # each peer runs a workstation with its whole simulated shop floor, time-scaled
    _floor =
      :erpc.call(
        node,
        CellPeers,
        :start_shop_floor,
        [[id: id, wc: "loopback:wc-#{id}", time_scale: 40]],
        60_000
      )

    Map.put(peer, :id, id)
  end

  @tag timeout: 300_000
  test "one client node drives a cycle on every workstation of the cell, and sees them all",
       %{peers: peers} do
    ids = Enum.map(peers, & &1.id)

    # :pg merges the groups of the peers asynchronously
    assert eventually(
             fn -> Enum.all?(ids, &Cell.whereis/1) end,
             10_000
           )

    for %{id: id, node: node} <- peers, do: assert(node(Cell.whereis(id)) == node)

    # the shipped machining cycle, all of it, on each workstation at once
    {:ok, script} = Script.parse_file(Vws.Ops.Demo.default_script())

    summaries =
      peers
      |> Enum.map(fn %{id: id} ->
        Task.async(fn ->
          {:ok, endpoint} = Cell.wc_endpoint(id)
          {:ok, wc} = Client.connect(endpoint, connect_timeout: 10_000)
          summary = Runner.run(wc, script, timeout: 60_000)
          {id, summary, wc}
        end)
      end)
      |> Task.await_many(180_000)

    for {id, summary, _wc} <- summaries do
      assert summary.result == :completed, "#{id}: #{inspect(summary.stopped)}"
      assert summary.steps_done == length(script.steps)
    end

    # the commands ran on the workstations' own nodes, on their own equipment: each GE-2000
    # machined the part once, and every robot command ended DONE there
    robot_commands = Enum.count(script.steps, &match?({:commands, [{"R", _} | _]}, &1.op))

    for %{id: id, node: node} <- peers do
      ge2000 = :erpc.call(node, Vws.Sim.Floor, :ge2000, [id])
      assert :erpc.call(node, Vws.Sim.GE2000, :state, [ge2000]).cycles == 1

      assert :erpc.call(node, Vws.CEC.Mailbox, :command_status, [id, :robot]) ==
               {robot_commands, :done}
    end

    # the cell view, here and from any peer, lists the three with their state and WC link
    view = Enum.filter(Cell.workstations(), &(&1.id in ids))

    assert Enum.map(view, &{&1.id, &1.node, &1.state, &1.wc, &1.wc_connected}) ==
             Enum.map(peers, &{&1.id, &1.node, :idle, "loopback:wc-#{&1.id}", true})

    [%{node: other} | _] = peers
    from_peer = :erpc.call(other, Cell, :workstations, [])
    assert Enum.map(Enum.filter(from_peer, &(&1.id in ids)), & &1.id) == ids

    # the dashboard's state carries the cell view too
    dashboard = Enum.filter(Vws.Ops.Web.State.build().cell, &(&1.id in ids))

    assert Enum.map(dashboard, &{&1.id, &1.node, &1.state, &1.wc_connected}) ==
             Enum.map(peers, &{&1.id, to_string(&1.node), "idle", true})

    text = Vws.Ops.Inspect.format_cell(view)
    for %{id: id, node: node} <- peers, do: assert(text =~ ~r/#{id}\s+#{node}\s+idle/)

    # a node that leaves takes its workstation out of the cell, and its WC hears the close
    [_, _, %{id: gone, peer: peer}] = peers
    {^gone, _, wc} = List.keyfind(summaries, gone, 0)
    :ok = :peer.stop(peer)
    assert eventually(fn -> Cell.whereis(gone) == nil end, 10_000)
    refute Enum.any?(Cell.workstations(), &(&1.id == gone))
    assert {:error, _} = Client.status(wc, "ROBOT_CMD")
  end
end
