defmodule Vws.Sim.MHSTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Interlock, Mailbox}
  alias Vws.Sim.{MHS, Plant}

  doctest MHS

  # the interlock needs only the workstation's mailboxes
  setup context do
    ws = "mhs-#{System.unique_integer([:positive])}"
    start_supervised!({Mailbox.Owner, workstation: ws})
    config = %{motion: %{tray_s: Map.get(context, :tray_s, 6.0)}}
    plant = start_supervised!({Plant, time_scale: 1000, config: config})

    mhs =
      start_supervised!(
        {MHS,
         [workstation: ws, plant: plant, timeout: 100, retry_ms: 20, poll_ms: 1] ++
           Map.get(context, :mhs, [])}
      )

    %{ws: ws, plant: plant, mhs: mhs}
  end

  test "moves a tray out and in; the lease is held only while it moves", ctx do
    assert MHS.move(ctx.mhs, 1, :out) == :ok
    refute Plant.snapshot(ctx.plant).trays[1].in_position
    assert MHS.move(ctx.mhs, 1, :in) == :ok
    assert Plant.snapshot(ctx.plant).trays[1].in_position
    assert Interlock.held(ctx.ws) == []

    assert [%{tray: 1, direction: :out, result: :ok}, %{tray: 1, direction: :in, result: :ok}] =
             MHS.history(ctx.mhs)
  end

  @tag tray_s: 300.0
  test "holds the tray's lease until the tray has stopped (rule 2a)", ctx do
    :ok = MHS.request(ctx.mhs, 2, :out)
    assert Vws.Test.Eventually.eventually(fn -> Plant.snapshot(ctx.plant).trays[2].moving end)
    assert Interlock.holder(ctx.ws, :tray2) == :mhs
    assert Interlock.acquire(ctx.ws, :tray2, :robot, 0) == {:error, "INTERLOCK TRAY2 HELD BY MHS"}
    assert Vws.Test.Eventually.eventually(fn -> not MHS.busy?(ctx.mhs) end)
    refute Plant.snapshot(ctx.plant).trays[2].moving
    assert Interlock.held(ctx.ws) == []
  end

  test "refused by the robot's lease (rule 2b) and by the lock relay", ctx do
    :ok = Interlock.acquire(ctx.ws, :tray1, :robot, 0)
    assert MHS.move(ctx.mhs, 1, :out) == {:error, "INTERLOCK TRAY1 HELD BY ROBOT"}
    :ok = Interlock.release(ctx.ws, :tray1, :robot)

    :ok = Plant.close_channel(ctx.plant, 208)
    assert MHS.move(ctx.mhs, 1, :out) == {:error, "TRAY 1 LOCKED"}
    assert Interlock.held(ctx.ws) == []
    assert Plant.snapshot(ctx.plant).trays[1].in_position
  end

  @tag mhs: [scenario: [{:move, 2, :out}, {:wait, 5}, {:move, 2, :in}, {:move, 1, :out}]]
  test "runs a scenario in order", ctx do
    assert Vws.Test.Eventually.eventually(fn -> length(MHS.history(ctx.mhs)) == 3 end)

    assert [
             %{tray: 2, direction: :out, result: :ok},
             %{tray: 2, direction: :in, result: :ok},
             %{tray: 1, direction: :out, result: :ok}
           ] = MHS.history(ctx.mhs)
  end
end
