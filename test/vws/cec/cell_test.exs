defmodule Vws.CEC.CellTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.Cell
  alias Vws.Links.Endpoint
  alias Vws.Test.{ObedientPartition, Workstation}
  import Vws.Test.Eventually

  doctest Vws.CEC.Cell

  test "a workstation is a member of the cell while it runs" do
    %{ws: ws, sup: sup} = Workstation.start(partitions: ObedientPartition.partitions())
    assert Cell.whereis(ws) == sup
    assert {ws, sup} in Cell.members()
    assert {:ok, %Endpoint{kind: :cell, name: ^ws}} = Cell.wc_endpoint(ws)

    assert eventually(fn -> match?({:ok, _, _}, Cell.resolve(ws)) end)
    assert {:ok, node, %Endpoint{kind: :loopback, name: "wc-" <> _}} = Cell.resolve(ws)
    assert node == node()

    :ok = stop_supervised({Vws.CEC.Workstation, ws})
    assert eventually(fn -> Cell.whereis(ws) == nil end)
    assert Cell.wc_endpoint(ws) == {:error, :not_found}
    assert Cell.resolve(ws) == {:error, :not_found}
  end

  test "the cell view: state, the WC link, commands in flight" do
    %{ws: ws} = Workstation.start(partitions: ObedientPartition.partitions(test: self()))
    view = fn -> Enum.find(Cell.workstations(), &(&1.id == ws)) end

    assert eventually(fn -> view.().state == :idle end)
    assert %{node: node, wc: "loopback:wc-" <> _, wc_connected: false} = view.()
    assert node == node()

    {:ok, endpoint} = Cell.wc_endpoint(ws)
    {:ok, wc} = Vws.Peers.WC.Client.connect(endpoint)
    assert {:ok, [{"R", 1}]} = Vws.Peers.WC.Client.send_commands(wc, [{"R", "DO MOVE SAFE"}])
    assert_receive {:executing, pid, 1, "DO MOVE SAFE"}

    assert %{state: :busy, wc_connected: true, commands: %{robot: {1, :executing}}} = view.()
    text = Vws.Ops.Inspect.format_cell(Enum.filter(Cell.workstations(), &(&1.id == ws)))
    assert text =~ ~r/#{ws}\s+#{node()}\s+busy\s+loopback:wc-#{ws} \(WC on\)\s+robot 0001/
    assert text =~ "1 workstation(s) on 1 node(s)"

    send(pid, {:result, :done})
    assert Vws.Peers.WC.Client.await_command(wc, "R", 1, 5_000) == :done
    assert %{state: :idle, commands: %{robot: {1, :done}}} = view.()
    Vws.Peers.WC.Client.close(wc)
  end

  test "a workstation that is not yet listening is :starting and cannot be resolved" do
    %{ws: ws} = Workstation.start(wc: nil, partitions: ObedientPartition.partitions())
    assert Cell.resolve(ws) == {:error, :not_listening}
    assert {:ok, endpoint} = Cell.wc_endpoint(ws)

    assert Vws.CEC.Cell.connect(endpoint) ==
             {:error, %Vws.Links.Transport.Error{reason: :not_listening}}
  end
end
