defmodule Vws.CellDistributedTest do
  # A cell of three `:peer` nodes, a workstation on each, driven by WC clients on this node.
  # Not async: this node becomes distributed for the module's duration.
  use ExUnit.Case, async: false

  @moduletag :distributed
  @moduletag timeout: 60_000

  alias Vws.Cell
  alias Vws.WC.{Client, Runner, Script}
  import Vws.Test.Eventually

  @peers 3

  setup_all do
    started_distribution? = ensure_distributed!()
    tag = System.unique_integer([:positive])

    peers =
      1..@peers
      |> Enum.map(fn i -> Task.async(fn -> start_peer(i, tag) end) end)
      |> Task.await_many(30_000)

    mesh!(Enum.map(peers, & &1.node))

    on_exit(fn ->
      for %{peer: peer} <- peers do
        try do
          :peer.stop(peer)
        catch
          :exit, _ -> :already_stopped
        end
      end

      if started_distribution?, do: :net_kernel.stop()
    end)

    %{peers: peers}
  end

  defp ensure_distributed! do
    if Node.alive?() do
      false
    else
      # distribution needs epmd; start it when none answers (it stays, as epmd does)
      if match?({:error, _}, :erl_epmd.names(~c"127.0.0.1")) do
        epmd =
          System.find_executable("epmd") ||
            Path.join([:code.root_dir(), "erts-#{:erlang.system_info(:version)}", "bin", "epmd"])

        {_, 0} = System.cmd(epmd, ["-daemon"])
        true = eventually(fn -> match?({:ok, _}, :erl_epmd.names(~c"127.0.0.1")) end, 5_000)
      end

      name = :"vws_test_#{System.unique_integer([:positive])}_#{System.pid()}@127.0.0.1"
      {:ok, _} = :net_kernel.start([name, :longnames])
      true
    end
  end

  # Every node connected to every other before the test, as in a deployment: connections that
  # form while the test runs make `global` drop some of them ("to prevent overlapping
  # partitions"), and :pg with them.
  defp mesh!(nodes) do
    for a <- nodes, b <- nodes, a < b, do: true = :erpc.call(a, Node, :connect, [b])

    all = [node() | nodes]

    true =
      eventually(
        fn ->
          Enum.all?(nodes, &(Enum.sort([&1 | :erpc.call(&1, Node, :list, [])]) == Enum.sort(all)))
        end,
        10_000
      )

    for n <- nodes, do: :ok = :erpc.call(n, :global, :sync, [], 10_000)
    :ok = :global.sync()
  end

  defp start_peer(i, tag) do
    # not linked to the starting task, which ends at once; on_exit stops it, and a peer halts
    # by itself when it loses this node
    {:ok, peer, node} =
      :peer.start(%{
        name: ~c"vws_cell_#{tag}_#{i}",
        host: ~c"127.0.0.1",
        longnames: true,
        args: [~c"-pa" | :code.get_path()],
        wait_boot: 30_000
      })

    :ok = :erpc.call(node, Application, :put_env, [:logger, :level, :warning])
    {:ok, _} = :erpc.call(node, Application, :ensure_all_started, [:vws], 30_000)
    :ok = :erpc.call(node, Logger, :configure, [[level: :warning]])

    id = "cell-#{tag}-#{i}"

    {:ok, _} =
      :erpc.call(node, Vws.Workstation, :start, [
        [
          id: id,
          wc: "loopback:wc-#{id}",
          partitions: Vws.Test.ObedientPartition.partitions()
        ]
      ])

    %{peer: peer, node: node, id: id}
  end

  @cycle """
  # a short cycle: two strings, a status, a pair of commands in one string
  R DO MOVE SAFE
  F CLOSE
  STATUS VISE
  R DO MOVE MV1 & G OPEN
  """

  test "one client node drives a cycle on every workstation of the cell, and sees them all",
       %{peers: peers} do
    ids = Enum.map(peers, & &1.id)

    # :pg merges the groups of the peers asynchronously
    assert eventually(
             fn -> Enum.all?(ids, &Cell.whereis/1) end,
             10_000
           )

    for %{id: id, node: node} <- peers, do: assert(node(Cell.whereis(id)) == node)

    {:ok, script} = Script.parse(@cycle)

    summaries =
      peers
      |> Enum.map(fn %{id: id} ->
        Task.async(fn ->
          {:ok, endpoint} = Cell.wc_endpoint(id)
          {:ok, wc} = Client.connect(endpoint, connect_timeout: 10_000)
          summary = Runner.run(wc, script, poll_interval: 10)
          {id, summary, wc}
        end)
      end)
      |> Task.await_many(30_000)

    for {id, summary, _wc} <- summaries do
      assert summary.result == :completed, "#{id}: #{inspect(summary.stopped)}"
      assert summary.steps_done == 4
    end

    # the commands ran on the workstations' own nodes
    for %{id: id, node: node} <- peers do
      assert :erpc.call(node, Vws.Mailbox, :command_status, [id, :robot]) == {2, :done}
      assert :erpc.call(node, Vws.Mailbox, :command_status, [id, :gripper]) == {1, :done}
      assert :erpc.call(node, Vws.Mailbox, :command_status, [id, :fixture]) == {1, :done}
    end

    # the cell view, here and from any peer, lists the three with their state and WC link
    view = Enum.filter(Cell.workstations(), &(&1.id in ids))

    assert Enum.map(view, &{&1.id, &1.node, &1.state, &1.wc, &1.wc_connected}) ==
             Enum.map(peers, &{&1.id, &1.node, :idle, "loopback:wc-#{&1.id}", true})

    [%{node: other} | _] = peers
    from_peer = :erpc.call(other, Cell, :workstations, [])
    assert Enum.map(Enum.filter(from_peer, &(&1.id in ids)), & &1.id) == ids

    # the dashboard's state carries the cell view too
    dashboard = Enum.filter(Vws.Web.State.build().cell, &(&1.id in ids))

    assert Enum.map(dashboard, &{&1.id, &1.node, &1.state, &1.wc_connected}) ==
             Enum.map(peers, &{&1.id, to_string(&1.node), "idle", true})

    text = Cell.format(view)
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
