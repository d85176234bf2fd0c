defmodule Vws.CycleScriptsTest do
  @moduledoc "The shipped cycle scripts run green against the whole simulated shop floor."
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.Peers.WC.Runner.Summary

  @moduletag timeout: 240_000

  for script <- ["table1.vws", "machining_cycle.vws"] do
    test "#{script} completes, every command DONE and every physical check true" do
      id = "cycle-#{System.unique_integer([:positive])}"
      on_exit(fn -> Vws.CEC.Workstation.stop(id) end)

      capture_io(fn ->
        result =
          Vws.Ops.Demo.run(
            id: id,
            wc: "loopback:#{id}",
            script: Path.join("priv/sims", unquote(script)),
            time_scale: 50,
            poll_interval: 5
          )

        send(self(), {:result, result})
      end)

      assert_received {:result, {:ok, summary, _floor, _client}}
      assert Summary.completed?(summary), "stopped: #{inspect(summary.stopped)}"
    end
  end
end
