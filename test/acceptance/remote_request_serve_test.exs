defmodule Vws.Acceptance.RemoteRequestServeTest do
  # Issue 27 as a user runs it: `iex -S mix vws.serve` in a terminal (tmux) with a program
  # library; the operator at the simulated GE-2000 asks for programs from the shell (the panel's
  # API), and the WC drip-feeds a library program restarted at a line — over the real WC port.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  @tag :tmux
  test "iex -S mix vws.serve: a remote request from the machine's panel, and DRIP_FEED(…/Nk) from the WC" do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()
    library = Path.join(System.tmp_dir!(), "vws-remote-#{System.unique_integer([:positive])}")
    on_exit(fn -> File.rm_rf(library) end)

    t =
      Acceptance.tmux_start(
        "iex -S mix vws.serve --wc-port #{wc} --http-port #{http} --time-scale 20 --library #{library}",
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.tmux_stop(t) end)

    Acceptance.tmux_await(t, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    Acceptance.tmux_await(t, ~r/iex\(1\)>/)

    program = ~S|"%\nO100\nG21 G90 G54\nT2 M6\nS800 M3\nG1 X1 F90\nX2\nX3\nM30\n%\n"|

    Acceptance.tmux_send(
      t,
      ~s|{:ok, _} = Vws.CEC.Library.store("VWS", "100", #{program}, source: "iex"); :stored|
    )

    Acceptance.tmux_await(t, ~r/^:stored$/m)

    # the operator asks for 100 (released: stored from iex) and for 101 (not in the library)
    sim = ~s|Vws.Sim.Floor.ge2000("VWS")|
    Acceptance.tmux_send(t, ~s|{Vws.Sim.GE2000.Panel.request_program(#{sim}, 100), :asked}|)
    Acceptance.tmux_await(t, ~r/^\{:ok, :asked\}$/m, 30_000)
    Acceptance.tmux_send(t, ~s|Vws.Sim.GE2000.program(#{sim}, "000100.PRO") == #{program}|)
    Acceptance.tmux_await(t, ~r/^true$/m)

    Acceptance.tmux_send(t, ~s|Vws.Sim.GE2000.Panel.request_program(#{sim}, 101)|)
    Acceptance.tmux_await(t, ~r/REQUEST REFUSED 000101\.PRO NOT IN LIBRARY"\}\}/, 30_000)
    Acceptance.tmux_send(t, ~s|hd(Vws.Sim.GE2000.state(#{sim}).messages)|)
    Acceptance.tmux_await(t, ~r/^"REQUEST REFUSED 000101\.PRO NOT IN LIBRARY"$/m)

    # and for version 2 of 100, a draft (not released): refused on the machine's screen too
    Acceptance.tmux_send(
      t,
      ~s|{:ok, _} = Vws.CEC.Library.store("VWS", "100", "%\\nO100\\nX9\\nM30\\n%\\n", source: "iex", state: :draft); :draft|
    )

    Acceptance.tmux_await(t, ~r/^:draft$/m)
    Acceptance.tmux_send(t, ~s|Vws.Sim.GE2000.Panel.request_program(#{sim}, 100, 2)|)
    Acceptance.tmux_await(t, ~r/REQUEST REFUSED 000100\.PRO VERSION 2 NOT RELEASED"\}\}/, 30_000)
    Acceptance.tmux_send(t, ~s|{hd(Vws.Sim.GE2000.state(#{sim}).messages), :on_screen}|)

    Acceptance.tmux_await(
      t,
      ~r/^\{"REQUEST REFUSED 000100\.PRO VERSION 2 NOT RELEASED", :on_screen\}$/m
    )

    # the WC: a drip feed of the library program restarted at line 7 ("X2"), and one past the end
    assert Acceptance.wc_request(wc, "*0001*M0001DRIP_FEED(000100.PRO/N7)*") =~ ~r/^05A0001\d{3}$/
    deadline = System.monotonic_time(:millisecond) + 60_000
    reply = Acceptance.await_command(wc, "MONARCH_CMD", 2, 1, deadline)
    assert reply =~ ~r/^\d\dS\d{4}0001DONE\d{3}$/, "#{reply}\n#{Acceptance.tmux_capture(t)}"
    # the preamble was shown before it went
    Acceptance.tmux_await(
      t,
      ~r/restarted at line 7, modal state restored by: G21 G90 G54 \/ T2 M6 \/ S800 M3 \/ G1 F90/
    )

    assert Acceptance.wc_request(wc, "*0003*M0002DRIP_FEED(000100.PRO/N10)*") =~
             ~r/^05A0003\d{3}$/

    deadline = System.monotonic_time(:millisecond) + 60_000
    reply = Acceptance.await_command(wc, "MONARCH_CMD", 4, 2, deadline)
    assert reply =~ ~r/0002ERROR RESTART LINE 10 BEYOND THE END \(LAST BLOCK 9\)/, reply

    Acceptance.tmux_keys(t, ["C-c"])
    Acceptance.tmux_await(t, ~r/SIGQUIT received \(Ctrl-C\)/, 30_000)
    assert Acceptance.tmux_await_exit(t, 60_000) == 0
  end
end
