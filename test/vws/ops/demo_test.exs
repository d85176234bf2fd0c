defmodule Vws.Ops.DemoTest do
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.Peers.WC.Client.Event
  alias Vws.Peers.WC.Runner.Summary

  doctest Vws.Ops.Demo, only: [printable: 1, readable: 1]

  # `mix vws.demo --ber 1e-4 --seed 3` stopped at its step 34: a reply with a flipped bit
  # (0xD6, not UTF-8) reached IO.puts, which raised
  test "a line damaged on the wire is printed with its damaged bytes as \\xNN, not a crash" do
    damaged = "11S0090ACTI" <> <<0xD6>> <> "E058"

    query = %Event{
      at: 5874,
      direction: :sent,
      kind: :status_query,
      line: "*0114*S0090MONARCH*104",
      meaning: "ask MONARCH"
    }

    answer = %Event{
      at: 5876,
      direction: :received,
      kind: :status,
      line: damaged,
      meaning: "MONARCH: ACTI" <> <<0xD6>> <> "E"
    }

    output =
      capture_io(fn ->
        printer = Vws.Ops.Demo.print_event(query, Vws.Ops.Demo.new_printer())
        Vws.Ops.Demo.print_event(answer, printer)
      end)

    assert output =~ ~r/^ +5\.876s  ← 11S0090ACTI\\xD6E058 +MONARCH: ACTI\\xD6E$/m
    assert String.valid?(output)
  end

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

  test "a status asked again with the same answer is folded into one row" do
    events =
      for {at, i} <- Enum.with_index([0, 10, 20, 30]), dir <- [:sent, :received] do
        if dir == :sent,
          do: %Event{
            at: at,
            direction: :sent,
            kind: :status_query,
            line: "*000#{i}*S000#{i}ROBOT_CMD*000",
            meaning: "ask ROBOT_CMD"
          },
          else: %Event{
            at: at + 1,
            direction: :received,
            kind: :status,
            line: "13S000#{i}0001EXECUTING000",
            meaning: "ROBOT 0001 EXECUTING"
          }
      end

    done = %Event{
      at: 45,
      direction: :received,
      kind: :status,
      line: "x",
      meaning: "ROBOT 0001 DONE"
    }

    query = %Event{
      at: 44,
      direction: :sent,
      kind: :status_query,
      line: "q",
      meaning: "ask ROBOT_CMD"
    }

    output =
      capture_io(fn ->
        Enum.reduce(
          events ++ [query, done],
          Vws.Ops.Demo.new_printer(),
          &Vws.Ops.Demo.print_event/2
        )
      end)

    assert [q0, a0, folded, q4, a4] = String.split(output, "\n", trim: true)
    assert q0 =~ "→ *0000*S0000ROBOT_CMD*000"
    assert a0 =~ "ROBOT 0001 EXECUTING"
    assert folded =~ "… asked 3 more times over 0.021s: same answer"
    assert q4 =~ "ask ROBOT_CMD"
    assert a4 =~ "ROBOT 0001 DONE"
  end
end
