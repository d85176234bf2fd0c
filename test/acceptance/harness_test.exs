defmodule Vws.Test.AcceptanceHarnessTest do
  # The harness itself (Vws.Test.Acceptance): a process group it starts is gone when stopped.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  doctest Vws.Test.Acceptance

  test "start/await/signal/await_exit on a shell, and stop kills the whole process group" do
    proc =
      Acceptance.start([
        "sh",
        "-c",
        "echo ready; trap 'echo got TERM; exit 3' TERM; sleep 60 >/dev/null 2>&1 & wait"
      ])

    assert ["ready"] = Acceptance.await(proc, ~r/ready/, 5_000)
    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 5_000) == 3
    assert Acceptance.output(proc) =~ "got TERM"

    proc = Acceptance.start(["sh", "-c", "sleep 300 & echo child $!; wait"])
    [_, child] = Acceptance.await(proc, ~r/child (\d+)/, 5_000)
    assert {_, 0} = System.cmd("kill", ["-0", child])
    Acceptance.stop(proc)

    assert Vws.Test.Eventually.eventually(fn ->
             {_, status} = System.cmd("kill", ["-0", child], stderr_to_stdout: true)
             status != 0
           end)
  end

  test "a tmux session: type, capture, stop" do
    t = Acceptance.tmux_start("sh")
    Acceptance.tmux_send(t, "echo $((6 * 7))")
    assert Acceptance.tmux_await(t, ~r/^42$/m, 10_000)
    Acceptance.tmux_stop(t)
  end
end
