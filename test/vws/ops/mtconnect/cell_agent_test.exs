defmodule Vws.Ops.MTConnect.CellAgentTest do
  # The MTConnect agent of one node serves every workstation of the cell: two on `:peer` nodes
  # and one here, each read on its own node. Not async: this node becomes distributed.
  use ExUnit.Case, async: false

  @moduletag :distributed
  @moduletag timeout: 60_000

  alias Vws.CEC.{Cell, Mailbox, Workstation}
  alias Vws.Test.{CellPeers, XMLLint}
  import Vws.Test.Eventually

  setup_all do
    started_distribution? = CellPeers.ensure_distributed!()
    on_exit(fn -> if started_distribution?, do: :net_kernel.stop() end)
    :ok
  end

  setup do
    tag = System.unique_integer([:positive])

    peers =
      [:a, :b]
      |> Enum.map(fn name ->
        Task.async(fn ->
          %{node: node} = peer = CellPeers.start!("vws_mtc_#{tag}_#{name}")
          id = "mtc-#{tag}-#{name}"
          {:ok, _} = :erpc.call(node, Workstation, :start, [[id: id, wc: nil]])
          {name, Map.merge(peer, %{id: id, os_pid: :erpc.call(node, System, :pid, [])})}
        end)
      end)
      |> Task.await_many(30_000)
      |> Map.new()

    CellPeers.mesh!([peers.a.node, peers.b.node])

    local = "mtc-#{tag}-local"
    {:ok, _} = Workstation.start(id: local, wc: nil)

    on_exit(fn ->
      Workstation.stop(local)

      for {_, %{peer: peer, os_pid: os_pid}} <- peers do
        # a peer the test stopped (SIGSTOP) must run again to be stopped
        System.cmd("kill", ["-CONT", os_pid], stderr_to_stdout: true)
        CellPeers.stop(peer)
      end
    end)

    ids = [peers.a.id, peers.b.id, local]
    # :pg merges the peers' groups asynchronously
    assert eventually(fn -> Enum.all?(ids, &Cell.whereis/1) end, 10_000)

    # what each workstation's mailboxes say, written on its own node
    :ok = :erpc.call(peers.a.node, Mailbox, :put_device, [peers.a.id, 10, "PALLET CLAMPED"])
    :ok = :erpc.call(peers.b.node, Mailbox, :put_device, [peers.b.id, 10, "PALLET NOT CLAMPED"])
    :ok = Mailbox.put_device(local, 3, "VISE JAWS ARE 0 MM APART AND VISE IS LOCKED PART IN VISE")

    # the agent serves the whole cell (no :workstations filter), as `mix vws.serve` starts it
    web =
      start_supervised!({Vws.Ops.Web, port: 0, interval: 100, node_timeout: 300}, id: make_ref())

    %{peers: peers, local: local, url: Vws.Ops.Web.url(web)}
  end

  defp get!(url) do
    {:ok, {{_, status, _}, _headers, body}} =
      :httpc.request(:get, {String.to_charlist(url), []}, [timeout: 30_000], body_format: :binary)

    {status, body}
  end

  # the current document, validated: %{data item id => value}
  defp current!(url) do
    {200, body} = get!(url <> "current")
    text = XMLLint.validate!(body, :streams)

    ~r{<\w+ dataItemId="([^"]+)" timestamp="[^"]+" sequence="\d+">([^<]*)</}
    |> Regex.scan(text, capture: :all_but_first)
    |> Map.new(fn [id, value] -> {id, value} end)
  end

  @tag :mtconnect_schemas
  test "/probe and /current list the workstations of every node, each read on its node",
       %{peers: peers, local: local, url: url} do
    {200, body} = get!(url <> "probe")
    probe = XMLLint.validate!(body, :devices)

    for id <- [peers.a.id, peers.b.id, local] do
      assert probe =~ ~s(<Device id="ws_#{id}" name="#{id}" uuid="vws-#{id}">)
    end

    v = current!(url)
    [a, b, l] = Enum.map([peers.a.id, peers.b.id, local], &"ws_#{&1}")

    assert {v["#{a}_avail"], v["#{b}_avail"], v["#{l}_avail"]} ==
             {"AVAILABLE", "AVAILABLE", "AVAILABLE"}

    assert v["#{a}_pallet_state"] == "LOCKED"
    assert v["#{b}_pallet_state"] == "UNLOCKED"
    assert v["#{l}_vise_state"] == "CLOSED"
    assert v["#{l}_vise_part"] == "PRESENT"

    # a change on a peer shows in the next document
    :ok = :erpc.call(peers.b.node, Mailbox, :put_device, [peers.b.id, 10, "PALLET CLAMPED"])
    assert current!(url)["#{b}_pallet_state"] == "LOCKED"

    # one device, by name, wherever it runs
    {200, body} = get!(url <> "#{peers.a.id}/current")
    text = XMLLint.validate!(body, :streams)
    assert text =~ ~s(<DeviceStream name="#{peers.a.id}")
    refute text =~ peers.b.id
  end

  @tag :mtconnect_schemas
  test "a node that does not answer is UNAVAILABLE, the others still answer; a stopped one is removed",
       %{peers: peers, local: local, url: url} do
    [a, b, l] = Enum.map([peers.a.id, peers.b.id, local], &"ws_#{&1}")
    assert current!(url)["#{a}_pallet_state"] == "LOCKED"

    # peer a stops answering (its OS process is stopped; the connection stays up)
    os_pid = peers.a.os_pid
    {_, 0} = System.cmd("kill", ["-STOP", os_pid])

    try do
      assert eventually(fn -> current!(url)["#{a}_avail"] == "UNAVAILABLE" end, 10_000)

      # every data item of a's device is UNAVAILABLE, not its last value; b and this node's are
      # read as before
      v = current!(url)

      assert for({id, value} <- v, String.starts_with?(id, a), value != "UNAVAILABLE", do: id) ==
               []

      assert v["#{b}_avail"] == "AVAILABLE"
      assert v["#{b}_pallet_state"] == "UNLOCKED"
      assert v["#{l}_vise_state"] == "CLOSED"
      {200, body} = get!(url <> "probe")
      assert XMLLint.validate!(body, :devices) =~ ~s(name="#{peers.a.id}")
    after
      System.cmd("kill", ["-CONT", os_pid])
    end

    # it answers again: its values come back (the periodic read asks it again)
    assert eventually(fn -> current!(url)["#{a}_pallet_state"] == "LOCKED" end, 10_000)

    # peer b goes away: its workstation leaves the cell, its device stays in the probe with
    # every item UNAVAILABLE, and the agent names it removed
    :ok = :peer.stop(peers.b.peer)
    assert eventually(fn -> Cell.whereis(peers.b.id) == nil end, 10_000)
    v = current!(url)
    assert v["#{b}_avail"] == "UNAVAILABLE"
    assert v["#{b}_pallet_state"] == "UNAVAILABLE"
    assert v["agent_device_removed"] == "vws-#{peers.b.id}"
    assert v["#{a}_avail"] == "AVAILABLE"
    assert v["#{l}_avail"] == "AVAILABLE"
    {200, body} = get!(url <> "probe")
    assert XMLLint.validate!(body, :devices) =~ ~s(name="#{peers.b.id}")
  end

  @tag :mtconnect_schemas
  test "a workstation on another node: every transition recorded when it happens, too",
       %{peers: peers} do
    a = start_supervised!({Vws.Ops.MTConnect.Agent, interval: 60_000}, id: make_ref())
    id = "ws_" <> peers.a.id
    %{next: next} = Vws.Ops.MTConnect.Agent.sequences(a)
    # its node's forwarder has sent the first snapshot
    assert eventually(fn -> MapSet.member?(:sys.get_state(a).followed, peers.a.id) end, 10_000)

    # 25 robot commands on peer a; the agent is not asked in between (its periodic read is a
    # minute away)
    for n <- 1..25 do
      :ok = :erpc.call(peers.a.node, Mailbox, :dispatch, [peers.a.id, :robot, n, "DO MOVE TRAY1"])
      :ok = :erpc.call(peers.a.node, Mailbox, :finish, [peers.a.id, :robot, n, :done])
    end

    # and the next answer has them all (the agent syncs with the forwarders first)
    {:ok, xml} = Vws.Ops.MTConnect.Agent.sample(a, next, 10_000)
    text = XMLLint.validate!(xml, :streams)

    exec =
      for [v] <-
            Regex.scan(~r{<Execution dataItemId="#{id}_robot_path_exec"[^>]*>(\w+)<}, text,
              capture: :all_but_first
            ),
          do: v

    assert Enum.count(exec, &(&1 == "ACTIVE")) == 25
    assert Enum.count(exec, &(&1 == "READY")) == 25

    # a download's progress on that node is the VMC's transfer message here, block by block
    for blocks <- 1..3 do
      progress = %{
        operation: :download,
        program: "001234.PRO",
        direction: :out,
        bytes: blocks * 256,
        total_bytes: 768,
        retries: 0,
        ended: blocks == 3
      }

      :ok =
        :erpc.call(peers.a.node, Vws.CEC.Events, :notify, [peers.a.id, :dnc_progress, progress])
    end

    assert eventually(fn ->
             {:ok, xml} = Vws.Ops.MTConnect.Agent.sample(a, next, 10_000)

             Regex.scan(
               ~r{dataItemId="#{id}_vmc_path_transfer"[^>]*>([^<]*)<},
               xml |> IO.iodata_to_binary(),
               capture: :all_but_first
             )
             |> List.flatten()
             |> Enum.filter(&(&1 =~ "001234"))
             |> length() == 3
           end)
  end

  test "a workstation on another node: its links' connection changes are recorded, too",
       %{peers: peers} do
    a = start_supervised!({Vws.Ops.MTConnect.Agent, interval: 60_000}, id: make_ref())
    ws = "#{peers.a.id}-tcp"
    id = "ws_" <> ws
    {:ok, _} = :erpc.call(peers.a.node, Workstation, :start, [[id: ws, wc: "tcp://127.0.0.1:0"]])
    on_exit(fn -> :erpc.call(peers.a.node, Workstation, :stop, [ws]) end)

    port =
      fn -> :erpc.call(peers.a.node, Vws.CEC.SunComm, :listening, [ws]) end
      |> Stream.repeatedly()
      |> Enum.find_value(fn
        nil -> Process.sleep(20) && nil
        endpoint -> endpoint.port
      end)

    conn = fn ->
      {:ok, xml} = Vws.Ops.MTConnect.Agent.current(a)

      case Regex.run(~r{dataItemId="#{id}_wc_link_conn"[^>]*>(\w+)<}, IO.iodata_to_binary(xml)) do
        [_, v] -> v
        nil -> nil
      end
    end

    # followed through its node's forwarder: the WC link listens
    assert eventually(fn -> conn.() == "LISTEN" end, 10_000)
    assert MapSet.member?(:sys.get_state(a).followed, ws)
    %{next: next} = Vws.Ops.MTConnect.Agent.sequences(a)

    # a WC comes and goes (a plain TCP client from this node), twice
    for _ <- 1..2 do
      {:ok, sock} = :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false])
      assert eventually(fn -> conn.() == "ESTABLISHED" end)
      :ok = :gen_tcp.close(sock)
      assert eventually(fn -> conn.() == "LISTEN" end)
    end

    {:ok, xml} = Vws.Ops.MTConnect.Agent.sample(a, next, 1000)

    states =
      for [v] <-
            Regex.scan(~r{dataItemId="#{id}_wc_link_conn"[^>]*>(\w+)<}, IO.iodata_to_binary(xml),
              capture: :all_but_first
            ),
          do: v

    assert states == ~w(ESTABLISHED LISTEN ESTABLISHED LISTEN)
  end
end
