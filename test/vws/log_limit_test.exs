defmodule Vws.LogLimitTest do
  use ExUnit.Case, async: true

  import ExUnit.CaptureLog
  alias Vws.LogLimit

  test "a condition is logged when it starts and when it ends, with its count; not in between" do
    log =
      capture_log(fn ->
        assert LogLimit.warning(:daq, "DAQ down") == :logged

        for _ <- 1..1_499,
            do: assert(LogLimit.warning(:daq, fn -> raise "not called" end) == :counted)

        assert LogLimit.on?(:daq)
        assert LogLimit.clear(:daq, "DAQ back") == :logged
        refute LogLimit.on?(:daq)
        assert LogLimit.clear(:daq, "DAQ back") == :off
      end)

    # (only this test's lines: the log also holds what tests running beside it log)
    assert [_, _] = String.split(log, "\n", trim: true) |> Enum.filter(&(&1 =~ "[warning] DAQ "))
    assert log =~ "[warning] DAQ down"
    assert log =~ ~r/\[warning\] DAQ back \(after 1,500 occurrences over \d+\.\d s\)/
  end

  test "conditions are independent, and each process has its own" do
    log =
      capture_log(fn ->
        LogLimit.warning({:relay, 1}, "relay 1 stuck")
        LogLimit.warning({:relay, 2}, "relay 2 stuck")
        task = Task.async(fn -> LogLimit.warning({:relay, 1}, "relay 1 stuck elsewhere") end)
        assert Task.await(task) == :logged
        LogLimit.clear({:relay, 2}, "relay 2 free")
      end)

    assert log =~ "relay 1 stuck"
    assert log =~ "relay 2 stuck"
    assert log =~ "relay 1 stuck elsewhere"
    assert log =~ "relay 2 free (after 1 occurrence over"
  end
end
