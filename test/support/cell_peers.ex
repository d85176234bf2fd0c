defmodule Vws.Test.CellPeers do
  @moduledoc """
  `:peer` nodes running the application, for tests of the cell (`Vws.CEC.Cell`). The test node is
  made distributed first (`ensure_distributed!/0`); each peer gets this node's code path.

      started? = CellPeers.ensure_distributed!()
      nodes = Enum.map(1..2, &CellPeers.start!("my_test_\#{tag}_\#{&1}"))
      CellPeers.mesh!(Enum.map(nodes, & &1.node))
      ...
      CellPeers.stop(peer); if started?, do: :net_kernel.stop()
  """

  import Vws.Test.Eventually

  @doc """
  Makes this node distributed (longnames, on 127.0.0.1), starting epmd when none answers (it
  stays, as epmd does). True when it started distribution (the caller stops it), false when the
  node already was distributed.
  """
  def ensure_distributed! do
    if Node.alive?() do
      false
    else
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

  @doc """
  Starts a peer node `name` with the application started (logger at warning):
  `%{peer: pid, node: node}`. Not linked to the caller; a peer halts by itself when it loses
  this node.
  """
  def start!(name) do
    {:ok, peer, node} =
      :peer.start(%{
        name: String.to_charlist(name),
        host: ~c"127.0.0.1",
        longnames: true,
        args: [~c"-pa" | :code.get_path()],
        wait_boot: 30_000
      })

    :ok = :erpc.call(node, Application, :put_env, [:logger, :level, :warning])
    {:ok, _} = :erpc.call(node, Application, :ensure_all_started, [:vws], 30_000)
    :ok = :erpc.call(node, Logger, :configure, [[level: :warning]])
    %{peer: peer, node: node}
  end

  @doc """
  Connects every node to every other before the test, as in a deployment: connections that form
  while the test runs make `global` drop some of them ("to prevent overlapping partitions"), and
  `:pg` with them.
  """
  def mesh!(nodes) do
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

  @doc """
  Called on a peer (`:erpc.call(node, CellPeers, :start_shop_floor, [opts])`): starts
  `Vws.Ops.Demo.start_shop_floor/1` there under a process of its own that lives as long as the node
  (the erpc process that calls this one ends at once, and the floor is linked to its starter).
  Returns the shop floor's map.
  """
  def start_shop_floor(opts) do
    caller = self()

    holder =
      spawn(fn ->
        send(caller, {:shop_floor, self(), Vws.Ops.Demo.start_shop_floor(opts)})
        Process.sleep(:infinity)
      end)

    receive do
      {:shop_floor, ^holder, {:ok, floor}} ->
        floor

      {:shop_floor, ^holder, {:error, reason}} ->
        raise "shop floor not started: #{inspect(reason)}"
    after
      30_000 -> raise "shop floor not started in 30 s"
    end
  end

  @doc "Stops a peer; one already stopped is fine."
  def stop(peer) do
    :peer.stop(peer)
  catch
    :exit, _ -> :already_stopped
  end
end
