defmodule Vws.Acceptance.IexServeTest do
  # `iex -S mix vws.serve` as the README runs it: in a terminal (tmux), with the shell used while
  # the simulated floor keeps serving, and stopped with Ctrl-\ (SIGQUIT) in order.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 180_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp pad(n), do: String.pad_leading(Integer.to_string(n), 4, "0")

  # Polls FIXTURE_CMD until command `number` ends; its status text.
  defp await_fixture(wc, seq, number, deadline) do
    reply = Acceptance.wc_request(wc, "*#{pad(seq)}*S#{pad(seq)}FIXTURE_CMD*")

    cond do
      reply =~ ~r/^\d\dS#{pad(seq)}#{pad(number)}(DONE|ERROR)/ ->
        reply

      System.monotonic_time(:millisecond) > deadline ->
        flunk("FIXTURE command #{number} did not end: #{reply}")

      true ->
        Process.sleep(100)
        await_fixture(wc, seq + 1, number, deadline)
    end
  end

  @tag :tmux
  test "iex -S mix vws.serve: the shell works and the floor keeps serving; Ctrl-\\ stops it in order" do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    t =
      Acceptance.tmux_start(
        "iex -S mix vws.serve --wc-port #{wc} --http-port #{http} --time-scale 20",
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.tmux_stop(t) end)

    Acceptance.tmux_await(t, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    Acceptance.tmux_await(t, ~r/iex\(1\)>/)

    # the shell is the user's: inspecting the workstation from it
    # (a prompt again after it: the shell answered, whatever overview printed — its content is
    # the dashboard/inspect tests' business)
    Acceptance.tmux_send(t, ~s|Vws.Inspect.overview("VWS")|)
    Acceptance.tmux_await(t, ~r/overview\("VWS"\)\n[\s\S]*iex\(\d+\)> *$/m)

    # the mix task's process has ended (the shell runs); the floor it started must not have
    # ended with it: a command verified on the simulated sensors (DAQ #1) still completes
    assert Acceptance.wc_request(wc, "*0001*F0001OPEN*") =~ ~r/^05A0001\d{3}$/
    deadline = System.monotonic_time(:millisecond) + 30_000
    reply = await_fixture(wc, 2, 1, deadline)
    assert reply =~ ~r/^\d\dS\d{4}0001DONE\d{3}$/, "#{reply}\n#{Acceptance.tmux_capture(t)}"

    refute Acceptance.tmux_capture(t) =~ "DAQ #1 NOT CONNECTED"

    # Ctrl-\ (SIGQUIT): a clean stop, in order, exit status 0
    # (the terminal's settings, for the failure message: Ctrl-\ is SIGQUIT only with isig)
    {tty, 0} = System.cmd("tmux", ["-L", t.socket, "display", "-p", "-t", "main", "\#{pane_tty}"])
    {stty, _} = System.cmd("stty", ["-a", "-F", String.trim(tty)], stderr_to_stdout: true)
    Acceptance.tmux_keys(t, ["C-\\"])
    Acceptance.tmux_await(t, ~r/SIGQUIT received/, 30_000)
    assert Acceptance.tmux_await_exit(t) == 0, stty
    pane = Acceptance.tmux_capture(t)
    assert [_, stop] = String.split(pane, "SIGQUIT received", parts: 2), pane
    refute stop =~ ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry|\[error\]/, pane
  end
end
