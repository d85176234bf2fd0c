defmodule Vws.Sim.VAL2Test do
  use ExUnit.Case, async: true

  alias Vws.Sim.VAL2
  alias Vws.Links.VAL
  import Vws.Test.Eventually

  # The CEC's logical-unit layer against the simulated controller over real DDCMP on TCP.
  setup context do
    test = self()

    sim =
      start_supervised!(
        {VAL2,
         time_scale: Map.get(context, :time_scale, 0.001),
         on_move: fn event -> send(test, {:on_move, event}) end},
        id: :sim
      )

    val = start_supervised!({VAL, ddcmp: [endpoint: VAL2.endpoint(sim)]}, id: :val)
    assert eventually(fn -> VAL.ready?(val) end)
    %{sim: sim, val: val}
  end

  test "a new connection while the old link is ending by itself takes over; nothing crashes", %{
    sim: sim
  } do
    ref = Process.monitor(sim)
    endpoint = VAL2.endpoint(sim)
    # The new connection is accepted while the simulator is busy; the old one then closes and
    # its link ends, its exit queued behind the new connection.
    :ok = :sys.suspend(sim)
    {:ok, conn} = Vws.Links.Transport.connect(endpoint)
    :ok = stop_supervised(:val)
    Process.sleep(100)
    :ok = :sys.resume(sim)

    refute_receive {:DOWN, ^ref, _, _, _}, 200
    Vws.Links.Transport.close(conn)
    val = start_supervised!({VAL, ddcmp: [endpoint: endpoint]}, id: :val)
    assert eventually(fn -> VAL.ready?(val) end)
    assert {:ok, _} = VAL.command(val, "WHERE")
  end

  @tag time_scale: 0.05
  test "the CEC's connection gone as a motion ends: the simulator carries on", %{
    sim: sim,
    val: val
  } do
    ref = Process.monitor(sim)
    endpoint = VAL2.endpoint(sim)
    motion = Task.async(fn -> VAL.motion(val, "DO MOVE VISE", 5_000) end)
    assert eventually(fn -> VAL2.info(sim).moving end)

    # the motion ends while the simulator is busy, and then its link ends, in that order
    :ok = :sys.suspend(sim)
    Process.sleep(500)
    :ok = stop_supervised(:val)
    assert {:error, _} = Task.await(motion)
    Process.sleep(100)
    :ok = :sys.resume(sim)

    refute_receive {:DOWN, ^ref, _, _, _}, 200
    val = start_supervised!({VAL, ddcmp: [endpoint: endpoint]}, id: :val)
    assert eventually(fn -> VAL.ready?(val) end)
    assert {:ok, _} = VAL.command(val, "WHERE")
  end

  test "WHERE answers SAFE's world coordinates and joints", %{val: val} do
    {:ok, text} = VAL.command(val, "WHERE")
    {:ok, %{world: world, joints: [j1, j2, j3 | _]}} = VAL.parse_where(text)
    assert world == [800.0, 0.0, 1200.0, 0.0, 180.0, 0.0]
    assert {j1, j2, j3} == {0.0, 29.36, 267.88}
  end

  test "a move reaches its location, tells the plant, and keeps every LUN rule", %{
    sim: sim,
    val: val
  } do
    assert :ok = VAL.motion(val, "DO MOVE VISE", 5_000)
    assert_received {:on_move, %{phase: :begin, volume: :vise, location: "VISE"}}
    assert_received {:on_move, %{phase: :complete, volume: :vise} = done}
    refute Map.has_key?(done, :carrying)

    assert :ok = VAL.motion(val, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)", 5_000)
    assert_received {:on_move, %{phase: :begin, volume: :tray1}}
    info = VAL2.info(sim)
    assert info.location == "MV1:TRANS(63.5,0,0,90,-90,0)"
    assert info.world == [650.0, -577.0, 1000.0, 0.0, 180.0, 0.0]
    assert info.volume == :tray1

    VAL2.set_carrying(sim, true)
    assert :ok = VAL.motion(val, "DO MOVE SAFE", 5_000)
    # leaving for SAFE counts on arrival
    assert_received {:on_move, %{phase: :begin, volume: :tray1, carrying: true}}
    assert_received {:on_move, %{phase: :complete, volume: :safe, carrying: true}}

    assert {:ok, ""} = VAL.command(val, "SPEED 100")
    assert VAL2.info(sim).speed == 100.0
    assert eventually(fn -> VAL.info(val).short_status =~ "SPEED 100.0" end)
    assert VAL2.info(sim).violations == 0

    assert VAL2.info(sim).commands ==
             ["DO MOVE VISE", "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)", "DO MOVE SAFE", "SPEED 100"]
  end

  test "the controller's numbered errors come back as {code, text}", %{sim: sim, val: val} do
    assert VAL.motion(val, "DO MOVE MV9") == {:error, {-301, "UNDEFINED LOCATION MV9"}}

    assert {:error, {-610, "LOCATION OUT OF REACH J2" <> _}} =
             VAL.motion(val, "DO MOVE SAFE:TRANS(0,0,2000,0,0,0)")

    assert VAL.command(val, "FLY") == {:error, {-302, "UNKNOWN COMMAND FLY"}}
    assert VAL.command(val, "EXECUTE NOPE") == {:error, {-304, "UNDEFINED PROGRAM NOPE"}}
    assert VAL2.info(sim).location == "SAFE"
  end

  test "EXECUTE runs a stored program to PROGRAM COMPLETE", %{sim: sim, val: val} do
    assert {:ok, ""} = VAL.command(val, "EXECUTE DEBURR", 10_000)
    assert VAL2.info(sim).location == "SAFE"
    assert {_, _} = Enum.find(VAL.info(val).last_async, &match?({:program_complete, _}, &1))
  end

  test "a hardware fault during a motion is a LUN 3 ERROR that ends it", %{sim: sim, val: val} do
    VAL2.fault(sim, -1002, "ARM POWER FAILURE")
    assert VAL.motion(val, "DO MOVES VISE") == {:error, {-1002, "ARM POWER FAILURE"}}
    assert_receive {:on_move, %{phase: :stopped}}
    assert VAL2.info(sim).location == nil
    # the monitor goes on
    assert :ok = VAL.motion(val, "DO MOVE SAFE")
  end

  @tag time_scale: 100.0
  test "a controller restart mid-motion ends the motion ERROR; it is not sent again", %{
    sim: sim,
    val: val
  } do
    move = Task.async(fn -> VAL.motion(val, "DO MOVE VISE", 30_000) end)
    assert eventually(fn -> VAL2.info(sim).moving end)
    VAL2.restart(sim)
    assert Task.await(move) == {:error, :peer_restarted}
    assert eventually(fn -> VAL.ready?(val) end)
    assert {:ok, _} = VAL.command(val, "WHERE")
    info = VAL2.info(sim)
    assert info.commands == ["DO MOVE VISE", "WHERE"]
    assert info.restarts == 1 and info.moving == false and info.violations == 0
  end

  test "a re-initialised link prompts again and goes on", %{sim: sim, val: val} do
    assert :ok = VAL.reinitialise(val)
    assert {:ok, _} = VAL.command(val, "WHERE", 5_000)
    assert :ok = VAL.reinitialise(val)
    assert :ok = VAL.motion(val, "DO MOVE VISE", 5_000)
    assert VAL2.info(sim).violations == 0
  end
end
