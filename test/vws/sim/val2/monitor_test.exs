defmodule Vws.Sim.VAL2.MonitorTest do
  use ExUnit.Case, async: true

  alias Vws.Sim.VAL2.Monitor

  doctest Monitor

  setup do
    %{m: Monitor.new(Monitor.load_config())}
  end

  defp motion(m, text) do
    {{:ok, ""}, [{:motion, plan}], m} = Monitor.command(m, text)
    {plan, m}
  end

  test "WHERE answers the world coordinates and joints of SAFE", %{m: m} do
    {{:ok, text}, [], ^m} = Monitor.command(m, "where")
    {:ok, %{world: world, joints: [j1, j2, j3 | _]}} = Vws.Links.VAL.parse_where(text)
    assert world == [800.0, 0.0, 1200.0, 0.0, 180.0, 0.0]
    # python3: atan2/hypot of the wrist centre (800, 0, 1450), shoulder at 1000, boom 650
    assert {j1, j2, j3} == {0.0, 29.36, 267.88}
    assert byte_size("0\r\n" <> text) <= Vws.Links.VAL.Message.max_text()
  end

  test "a joint move takes the slowest joint's time over SPEED; a straight one its path length",
       %{m: m} do
    # python3: boom 267.878 -> 554.159 mm at 500 mm/s, SPEED 50
    {plan, _} = motion(m, "DO MOVE VISE")
    assert plan.kind == :joint
    assert_in_delta plan.duration_ms, 1145.125881379755, 1.0e-6

    # python3: |(650, 640.5, 700) - (800, 0, 1200)| = 826.281 mm at 500 mm/s, SPEED 50
    {plan, _} = motion(m, "DO MOVES TRAY2")
    assert plan.kind == :straight
    assert_in_delta plan.duration_ms, 3305.1239008545504, 1.0e-6

    {{:ok, ""}, [], fast} = Monitor.command(m, "SPEED 100")
    {plan, _} = motion(fast, "DO MOVE VISE")
    assert_in_delta plan.duration_ms, 1145.125881379755 / 2, 1.0e-6
  end

  test "a compound transformation reaches the point of seed Table 1 step 1", %{m: m} do
    {plan, m} = motion(m, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)")
    m = Monitor.complete_motion(m)
    assert plan.target == "MV1:TRANS(63.5,0,0,90,-90,0)"
    {world, _} = Monitor.coordinates(m, nil)
    assert world == [650.0, -577.0, 1000.0, 0.0, 180.0, 0.0]
    assert Monitor.volume(m, nil) == :tray1
  end

  test "APPRO stops short along the tool axis, DEPART backs off from where the tool is", %{m: m} do
    {_, m} = motion(m, "DO APPRO TRAY1, 100")
    m = Monitor.complete_motion(m)
    assert {[650.0, -450.0, 800.0 | _], _} = Monitor.coordinates(m, nil)
    assert m.location == nil
    {_, m} = motion(m, "DO APPROS TRAY1, 0")
    m = Monitor.complete_motion(m)
    assert m.location == "TRAY1"
    {plan, m} = motion(m, "DO DEPARTS 50")
    assert plan.kind == :straight
    m = Monitor.complete_motion(m)
    assert {[650.0, -450.0, 750.0 | _], _} = Monitor.coordinates(m, nil)
  end

  test "the numbered errors", %{m: m} do
    assert {{:error, -301, "UNDEFINED LOCATION MV9"}, [], _} = Monitor.command(m, "DO MOVE MV9")
    assert {{:error, -302, "UNKNOWN COMMAND JUMP"}, [], _} = Monitor.command(m, "JUMP")
    assert {{:error, -302, _}, [], _} = Monitor.command(m, "DO FLY SAFE")
    assert {{:error, -303, "INVALID ARGUMENT 0"}, [], _} = Monitor.command(m, "SPEED 0")
    # the WC's "/" is not VAL II syntax
    assert {{:error, -303, _}, [], _} = Monitor.command(m, "DO APPRO TRAY1/50")
    assert {{:error, -303, _}, [], _} = Monitor.command(m, "DO MOVE SAFE:TRANS(1,2,3)")
    assert {{:error, -304, "UNDEFINED PROGRAM NOPE"}, [], _} = Monitor.command(m, "EXECUTE NOPE")

    assert {{:error, -610, "LOCATION OUT OF REACH J2 " <> _}, [], _} =
             Monitor.command(m, "DO MOVE SAFE:TRANS(0,0,2000,0,0,0)")

    # both ends reachable (j1 = ±143°), the line between passes behind the base (j1 = 180°)
    {_, m2} = motion(m, "DO MOVE SAFE:TRANS(1400,450,400,0,0,0)")
    m2 = Monitor.complete_motion(m2)

    assert {{:error, -611, "STRAIGHT LINE PATH OUT OF REACH"}, [], _} =
             Monitor.command(m2, "DO MOVES SAFE:TRANS(1400,-450,400,0,0,0)")

    # the joint-interpolated move swings the other way round and is fine
    assert {{:ok, ""}, [{:motion, _}], _} =
             Monitor.command(m2, "DO MOVE SAFE:TRANS(1400,-450,400,0,0,0)")

    {_, moving} = motion(m, "DO MOVE VISE")

    assert {{:error, -640, "MOTION ALREADY IN PROGRESS"}, [], _} =
             Monitor.command(moving, "DO MOVE SAFE")

    assert {{:ok, _}, [], _} = Monitor.command(moving, "WHERE")

    {{:ok, ""}, [{:program, "PARK"}], running} = Monitor.command(m, "EXECUTE PARK")
    assert {{:error, -641, _}, [], _} = Monitor.command(running, "DO MOVE SAFE")
  end

  test "a program runs its steps one after another", %{m: m} do
    {{:ok, ""}, [{:program, "DEBURR"}], m} = Monitor.command(m, "EXECUTE DEBURR")

    {m, targets} =
      Stream.iterate(0, & &1)
      |> Enum.reduce_while({m, []}, fn _, {m, acc} ->
        case Monitor.next_step(m) do
          {:motion, plan, m} -> {:cont, {Monitor.complete_motion(m), [plan.target | acc]}}
          {:done, m} -> {:halt, {m, Enum.reverse(acc)}}
        end
      end)

    assert length(targets) == 5
    assert List.last(targets) == "SAFE"
    assert m.program == nil and m.location == "SAFE"
  end

  test "a stopped motion leaves the arm part way; a restart resets the speed", %{m: m} do
    {{:ok, ""}, [], m} = Monitor.command(m, "SPEED 80")
    {_, m} = motion(m, "DO MOVES VISE")
    m = Monitor.restart(m, 0.5)
    assert m.motion == nil and m.speed == 50.0 and m.location == nil
    assert {[1000.0, 0.0, 1025.0 | _], _} = Monitor.coordinates(m, nil)
  end
end
