defmodule Vws.CEC.Interlock.WorkVolumesTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.Interlock.WorkVolumes
  alias Vws.Sim.VAL2.Monitor

  doctest WorkVolumes

  # the plant's volumes that lie in each interlocked volume
  @interlocked %{
    vise: :table,
    table: :table,
    pallet: :table,
    tray1: :tray1,
    tray2: :tray2,
    safe: :safe
  }

  setup do
    config = Monitor.load_config()
    %{wv: WorkVolumes.load(), config: config, monitor: Monitor.new(config)}
  end

  test "every location the simulated robot knows lies where the CEC believes it does", ctx do
    for {name, _} <- ctx.config.locations do
      {:ok, plan} = Monitor.plan(ctx.monitor, "MOVE " <> name)
      geometric = Map.fetch!(@interlocked, Monitor.volume(plan.to, ctx.monitor.config))
      assert WorkVolumes.location(ctx.wv, name) == {:ok, geometric}, name
    end
  end

  test "the compound locations of the scripts lie in the volume of their frame", ctx do
    for trans <- [
          "MV1:TRANS(63.5,0,0,90,-90,0)",
          "MV1:TRANS(63.5,-300,0,90,-90,0)",
          "MV2:TRANS(0,-300,0,90,-90,0)",
          "MV3:TRANS(0,-250,0,90,-90,0)",
          "MV3:TRANS(20,-250,0,90,-90,0)"
        ] do
      {:ok, plan} = Monitor.plan(ctx.monitor, "MOVE " <> trans)
      geometric = Map.fetch!(@interlocked, Monitor.volume(plan.to, ctx.monitor.config))
      {:ok, {:do, :move, loc}} = Vws.Codecs.Commands.parse(:robot, "DO MOVE " <> trans)
      assert WorkVolumes.location(ctx.wv, loc) == {:ok, geometric}, trans
    end
  end

  test "each program enters only the volumes listed for it and ends where it says", ctx do
    for {name, _steps} <- ctx.config.programs do
      {:ok, %{enters: enters, ends: ends}} = WorkVolumes.program(ctx.wv, name)
      {{:ok, _}, [{:program, ^name}], m} = Monitor.command(ctx.monitor, "EXECUTE " <> name)
      visited = run_program(m, [])
      assert Enum.all?(visited, &(&1 in [:safe | enters])), "#{name}: #{inspect(visited)}"
      assert List.last(visited) == ends
    end
  end

  defp run_program(m, acc) do
    case Monitor.next_step(m) do
      {:motion, plan, m} ->
        volume = Map.fetch!(@interlocked, Monitor.volume(plan.to, m.config))
        run_program(Monitor.complete_motion(m), acc ++ [volume])

      {:done, _m} ->
        acc
    end
  end

  test "a map of the wrong shape is refused" do
    assert_raise ArgumentError, fn -> WorkVolumes.load(%{locations: %{"X" => "table"}}) end
    assert WorkVolumes.load(%{default: :safe}) |> WorkVolumes.location("ANY") == {:ok, :safe}
  end
end
