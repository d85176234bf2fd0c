defmodule Vws.CycleScriptsTest do
  @moduledoc """
  The shipped cycle scripts run green against the whole simulated shop floor (the demo's, which
  `mix vws.serve` starts too), and do what they claim: the plant's true state after each — where
  the part is — is what the script says, and a script whose part is missing stops at its checks.
  """
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.Peers.WC.{Client, Runner, Script}
  alias Vws.Peers.WC.Runner.Summary
  alias Vws.Sim.{Floor, Plant}

  @moduletag timeout: 240_000

  # where the plant has parts: the places that hold one
  defp parts(id) do
    for {where, part} <- Plant.snapshot(Floor.plant(id)).parts, part, do: where
  end

  defp demo(id, script, opts \\ []) do
    on_exit(fn -> Vws.CEC.Workstation.stop(id) end)

    capture_io(fn ->
      result =
        Vws.Ops.Demo.run(
          [
            id: id,
            wc: "loopback:#{id}",
            script: script,
            time_scale: 50,
            poll_interval: 5
          ] ++ opts
        )

      send(self(), {:result, result})
    end)

    assert_received {:result, {:ok, summary, _floor, _client}}
    summary
  end

  for script <- ["table1.vws", "machining_cycle.vws"] do
    test "#{script} completes, every command DONE and every physical check true; the part ends in tray #1" do
      id = "cycle-#{System.unique_integer([:positive])}"
      # (readings a loaded host's DAQ #1 answered late show NO DATA for a moment: an EXPECT
      # that must be true keeps asking for 10 s, not 2 — once seen, GRIPPER NO DATA at load)
      summary = demo(id, Path.join("priv/sims", unquote(script)), expect_grace: 10_000)
      assert Summary.completed?(summary), "stopped: #{inspect(summary.stopped)}"
      assert parts(id) == [:tray1]
      assert Vws.CEC.Interlock.held(id) == []
      assert Plant.collisions(Floor.plant(id)) == []
    end
  end

  @tag :tmp_dir
  test "table1.vws checks the gripper: without its set-up (no part in the vise) it stops at the " <>
         "gripper closed on nothing",
       %{tmp_dir: tmp} do
    text = File.read!("priv/sims/table1.vws")
    [before, rest] = String.split(text, "# --- Set-up", parts: 2)
    [_setup, task] = String.split(rest, "# --- Table 1's task goes on", parts: 2)
    path = Path.join(tmp, "table1-no-setup.vws")
    File.write!(path, before <> "# --- Table 1's task goes on" <> task)

    id = "cycle-#{System.unique_integer([:positive])}"
    summary = demo(id, path)
    refute Summary.completed?(summary)
    assert summary.stopped.source =~ ~r/^EXPECT GRIPPER ~ \^FINGERS ARE/
    assert summary.stopped.reason =~ "FINGERS ARE 0.0 MM APART"
  end

  test "a cycle that fails holds the table; recover.vws gives every lease up and the next cycle runs" do
    id = "cycle-#{System.unique_integer([:positive])}"
    on_exit(fn -> Vws.CEC.Workstation.stop(id) end)
    {:ok, floor} = Vws.Ops.Demo.start_shop_floor(id: id, wc: "loopback:#{id}", time_scale: 50)
    {:ok, client} = Client.connect(floor.wc)
    plant = Floor.plant(id)

    run = fn name ->
      {:ok, script} = Script.parse_file("priv/sims/" <> name)
      Runner.run(client, script, poll_interval: 5)
    end

    # the vise's CLOSE valve stuck: the cycle stops at F CLOSE, the arm in the vise
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :vise_close_valve)
    failed = run.("machining_cycle.vws")
    refute Summary.completed?(failed)
    assert failed.stopped.source == "F CLOSE"
    held = for %{volume: v, holder: h} <- Vws.CEC.Interlock.held(id), do: {v, h}
    assert {:table, :robot} in held and {:table, :fixture} in held

    :ok = Plant.clear_fault(plant, :stuck_valve)
    recovered = run.("recover.vws")
    assert Summary.completed?(recovered), "stopped: #{inspect(recovered.stopped)}"
    assert Vws.CEC.Interlock.held(id) == []
    assert Plant.collisions(plant) == []

    # the operator takes the blank from the gripper and puts it back in tray #1
    assert parts(id) == [:gripper]
    :ok = Plant.set_part(plant, :gripper, false)
    :ok = Plant.set_part(plant, :tray1, true)

    passed = run.("machining_cycle.vws")
    assert Summary.completed?(passed), "stopped: #{inspect(passed.stopped)}"
    assert parts(id) == [:tray1]
    assert Vws.CEC.Interlock.held(id) == []
  end
end
