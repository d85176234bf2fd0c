defmodule Vws.Acceptance.ServeTest do
  # `mix vws.serve` as the README runs it: a real OS process with its simulated floor, driven
  # through the real WC TCP link and real HTTP, stopped with SIGTERM.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 180_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  # What a clean stop never prints.
  @crash ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry|\[error\]/

  # The output from the signal on: the stop must be clean (what ran before is other tests' job).
  def after_signal(output) do
    case String.split(output, ~r/SIGTERM received/, parts: 2) do
      [_, rest] -> rest
      [_] -> flunk("the node did not say it received SIGTERM:\n#{output}")
    end
  end

  defp serve(extra) do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "#{http}"] ++ extra,
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    Acceptance.await(proc, ~r/Dashboard and MTConnect agent: http:\/\/127\.0\.0\.1:#{http}\//)
    %{proc: proc, wc: wc, http: http}
  end

  test "mix vws.serve: a status and a command over TCP, the dashboard's state and MTConnect over HTTP, SIGTERM stops it cleanly" do
    %{proc: proc, wc: wc, http: http} = serve(["--time-scale", "20"])

    # a status string: answered at once from the mailboxes
    assert Acceptance.wc_request(wc, "*0001*S0001ROBOT_CMD*") =~ ~r/^\d\dS0001.*\d{3}$/

    # a real command, run on the simulated floor and verified on its sensors
    assert Acceptance.wc_request(wc, "*0002*F0001OPEN*") =~ ~r/^05A0002\d{3}$/
    deadline = System.monotonic_time(:millisecond) + 30_000

    assert Acceptance.await_command(wc, "FIXTURE_CMD", 3, 1, deadline) =~
             ~r/^\d\dS\d{4}0001DONE\d{3}$/

    # the integrator's command line (README): a command to its end, exit status 0
    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{wc}", "--command", "F OPEN"],
        env: [{"MIX_ENV", "dev"}]
      )

    assert Acceptance.await_exit(cli, 60_000) == 0, Acceptance.output(cli)
    assert Acceptance.output(cli) =~ ~r/F0002 OPEN: DONE/

    assert {200, state} = Acceptance.http_get(http, "/api/state")
    assert state =~ ~s("workstations")
    assert {200, current} = Acceptance.http_get(http, "/current")
    assert current =~ "MTConnectStreams"
    assert current =~ ~s(name="VWS")

    Acceptance.signal(proc, "TERM")
    status = Acceptance.await_exit(proc, 30_000)
    output = Acceptance.output(proc)
    refute after_signal(output) =~ @crash, output
    refute output =~ ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry/, output
    assert status == 0, output
  end
end
