defmodule Vws.Sim.FloorTest do
  use ExUnit.Case, async: true

  doctest Vws.Sim.Floor

  test "the demo's shop floor: a workstation wired to the floor polls the plant" do
    ws = "floor-#{System.unique_integer([:positive])}"

    {:ok,
     %{
       name: "plant + DAQ #1, GE-2000, VAL II, material handling",
       links: links,
       partitions: partitions
     }} = Vws.Sim.Floor.shop_floor(workstation: ws, time_scale: 100)

    start_supervised!({Vws.Workstation, id: ws, wc: nil, links: links, partitions: partitions})

    assert Vws.Test.Eventually.eventually(fn ->
             Vws.Status.answer(ws, "VACUUM") == "VACUUM IS OFF"
           end)

    :ok = Vws.Sim.Plant.close_channel(Vws.Sim.Floor.plant(ws), 207)

    assert Vws.Test.Eventually.eventually(fn ->
             Vws.Status.answer(ws, "VACUUM") == "VACUUM IS ON"
           end)
  end
end
