defmodule Vws.Ops.DemoTest do
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.Peers.WC.Runner.Summary

  test "the demo starts the shop floor, runs the cycle and prints the dialogue and the summary" do
    id = "demo-#{System.unique_integer([:positive])}"
    on_exit(fn -> Vws.CEC.Workstation.stop(id) end)

    output =
      capture_io(fn ->
        result = Vws.Ops.Demo.run(id: id, wc: "loopback:#{id}", time_scale: 50, poll_interval: 5)
        send(self(), {:result, result})
      end)

    assert_received {:result, {:ok, summary, floor, _client}}
    {:ok, script} = Vws.Peers.WC.Script.parse_file(Vws.Ops.Demo.default_script())
    first = hd(script.steps)

    assert output =~ "VWS demo — workstation #{id}, SUN_COMM serves the WC on loopback:#{id}"
    assert output =~ "── step 1 of #{length(script.steps)}, line #{first.line}: R DISABLE_TRAY1"

    assert output =~
             ~r/^ +\d+\.\d{3}s  → \*0001\*R0001DISABLE_TRAY1\*\d{3} +string 0001: ROBOT 0001$/m

    assert output =~ ~r/^ +\d+\.\d{3}s  ← 05A0001\d{3} +ack: string 0001 received intact$/m
    assert output =~ ~r/^ +\d+\.\d{3}s  → \*0002\*S0001ROBOT_CMD\*\d{3} +ask ROBOT_CMD$/m
    assert output =~ "== Summary =="

    [result] = Regex.run(~r/^result: +(.*)$/m, output, capture: :all_but_first)

    if Summary.completed?(summary) do
      assert result == "COMPLETED"
    else
      %{line: line, reason: reason} = summary.stopped
      assert result =~ "STOPPED at line #{line} (step #{summary.stopped.step} of "
      assert String.ends_with?(result, reason)
    end

    # what is not simulated is said, and is what stops the cycle
    if {:robot, "VAL II"} in floor.unlinked do
      assert output =~ "ROBOT has no link to the VAL II: its commands end ERROR NO LINK TO VAL II"

      assert output =~
               ~r/← \d\dS\d{4}0001ERROR NO LINK TO VAL II\d{3} +ROBOT 0001 ERROR NO LINK TO VAL II$/m

      assert summary.stopped.reason == "ROBOT command 0001 ended ERROR NO LINK TO VAL II"
    end
  end

  test "a script that does not parse is refused with its line" do
    assert {:error, message} = Vws.Ops.Demo.run(script: "test/no/such.vws")
    assert message =~ "test/no/such.vws: cannot read the script"
  end
end
