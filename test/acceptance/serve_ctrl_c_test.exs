defmodule Vws.Acceptance.ServeCtrlCTest do
  # One Ctrl-C in the terminal running `mix vws.serve` (under tmux, as a user runs it): an ordered
  # stop — never the BEAM's BREAK menu, which freezes the controller (no WC reply, no HTTP
  # answer, DAQ #1 not polled) while equipment may be moving. The terminal's settings are given
  # back when it exits.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 180_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp pane_tty(t) do
    {out, 0} =
      System.cmd("tmux", ["-L", t.socket, "list-panes", "-t", "main", "-F", "\#{pane_tty}"])

    String.trim(out)
  end

  defp stty(tty) do
    {out, 0} = System.cmd("stty", ["-F", tty, "-a"], stderr_to_stdout: true)
    out
  end

  @tag :tmux
  test "mix vws.serve: one Ctrl-C stops it in order (status 0), and the terminal is given back" do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    # typed into an interactive shell, as a user does; the shell shows the terminal's settings
    # once it has exited, as the user's next command finds them
    t = Acceptance.tmux_start("bash --norc --noprofile -i", env: [{"MIX_ENV", "dev"}])
    on_exit(fn -> Acceptance.tmux_stop(t) end)
    tty = pane_tty(t)
    assert stty(tty) =~ ~r/intr = \^C;/

    Acceptance.tmux_send(
      t,
      "mix vws.serve --wc-port #{wc} --http-port #{http} --time-scale 20; " <>
        ~s(echo "serve exited $?"; stty -a)
    )

    Acceptance.tmux_await(t, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    # the banner says how to stop it: Ctrl-C, no extra flag typed
    Acceptance.tmux_await(t, ~r/Stop: Ctrl-C or kill \d+ \(in order\)/)
    assert Acceptance.wc_request(wc, "*0001*S0001ROBOT_CMD*") =~ ~r/^\d\dS00010000NONE\d{3}$/
    assert {200, ~s({"status":"ok"})} = Acceptance.http_get(http, "/health")

    # while it runs, Ctrl-C is the terminal's QUIT character (SIGQUIT, handled) and INTR is none
    running = stty(tty)
    assert running =~ ~r/intr = <undef>;/, running
    assert running =~ ~r/quit = \^C;/, running

    Acceptance.tmux_keys(t, ["C-c"])
    Acceptance.tmux_await(t, ~r/SIGQUIT received \(Ctrl-C\): stopping/, 30_000)
    Acceptance.tmux_await(t, ~r/^serve exited 0$/m, 60_000)
    Acceptance.tmux_await(t, ~r/^intr = /m)

    pane = Acceptance.tmux_capture(t)
    refute pane =~ "BREAK: (a)bort", pane
    assert [_, stop] = String.split(pane, "SIGQUIT received", parts: 2), pane
    refute stop =~ ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry|\[error\]/, pane

    # the terminal's own settings again: Ctrl-C interrupts the user's next program as usual
    [_, after_exit] = String.split(pane, ~r/^serve exited 0$/m, parts: 2)
    assert after_exit =~ ~r/intr = \^C; quit = \^\\;/, pane
  end
end
