defmodule Vws.Acceptance.ReleaseTest do
  # The release as the README deploys it: `MIX_ENV=prod mix release`, started with its
  # environment (VWS_WC, VWS_DAQ1, VWS_HTTP_PORT, VWS_LOG_DIR), driven over the real WC TCP link
  # and HTTP, by bin/vws-wc too, and stopped with SIGTERM. DAQ #1 is a simulated one in this
  # test's VM (with the GE-2000 the FIXTURE interlock reads), reached over TCP as real ones are.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :release
  @moduletag timeout: 600_000

  setup_all do
    # built once per run (`MIX_ENV=prod mix release`), shared with Vws.ReleaseTest
    %{release: Acceptance.release()}
  end

  @tag :tmp_dir
  test "the release: started from its environment, a WC command to DONE on DAQ #1, HTTP, bin/vws-wc, bin/vws-library, logs to a file at info, SIGTERM stops it cleanly",
       %{release: release, tmp_dir: tmp} do
    ws = "REL#{System.unique_integer([:positive])}"

    start_supervised!(
      {Vws.Sim.Floor,
       workstation: ws, time_scale: 20, daq1: "tcp://127.0.0.1:0", daq2: false, ge2000: true}
    )

    daq1 = Vws.Sim.Floor.daq1_endpoint(ws)
    wc = Acceptance.free_port()
    http = Acceptance.free_port()
    log_dir = Path.join(tmp, "log")
    data = Path.join(tmp, "data")

    proc =
      Acceptance.start([Path.join(release, "bin/vws"), "start"],
        env: [
          {"VWS_ID", "VWS1"},
          {"VWS_WC", "tcp://127.0.0.1:#{wc}"},
          {"VWS_DAQ1", daq1},
          {"VWS_GE2000", Vws.Sim.GE2000.endpoint(Vws.Sim.Floor.ge2000(ws))},
          {"VWS_HTTP_PORT", "#{http}"},
          {"VWS_LOG_DIR", log_dir},
          {"VWS_DATA_DIR", data},
          {"RELEASE_DISTRIBUTION", "none"}
        ]
      )

    on_exit(fn -> Acceptance.stop(proc) end)

    Acceptance.await(
      proc,
      ~r/SUN_COMM listening for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/,
      60_000
    )

    assert Acceptance.wc_request(wc, "*0001*S0001FIXTURE_CMD*") =~ ~r/^\d\dS00010000NONE\d{3}$/

    # the integrator's command line of the release: a command verified on DAQ #1's sensors
    cli =
      Acceptance.start(
        [
          Path.join(release, "bin/vws-wc"),
          "--endpoint",
          "tcp://127.0.0.1:#{wc}",
          "--command",
          "F OPEN"
        ],
        env: [{"VWS_LOG_DIR", "off"}]
      )

    assert Acceptance.await_exit(cli, 60_000) == 0, Acceptance.output(cli)
    assert Acceptance.output(cli) =~ "F0001 OPEN: DONE"
    assert Acceptance.wc_request(wc, "*0002*S0002FIXTURE_CMD*") =~ ~r/^\d\dS00020001DONE\d{3}$/

    assert {200, current} = Acceptance.http_get(http, "/current")
    assert current =~ ~s(name="VWS1")
    assert {200, _state} = Acceptance.http_get(http, "/api/state")

    # the release's program library (issue 18): a program imported with bin/vws-library, sent
    # by name from the WC, and the machine found holding it
    program = Path.join(tmp, "4711.nc")
    File.write!(program, "%\nO4711\nN10 G00 X0 Y0\nN20 M30\n%\n")

    library = fn args ->
      p =
        Acceptance.start([Path.join(release, "bin/vws-library") | args],
          env: [{"VWS_ID", "VWS1"}, {"VWS_DATA_DIR", data}]
        )

      {Acceptance.await_exit(p, 60_000), Acceptance.output(p)}
    end

    assert {0, out} = library.(["import", program])
    assert out =~ "stored 004711.PRO v1"
    assert Acceptance.wc_request(wc, "*0003*M0001DOWNLOAD_GE(004711.PRO)*") =~ ~r/^05A0003\d{3}$/
    deadline = System.monotonic_time(:millisecond) + 60_000

    assert Acceptance.await_command(wc, "MONARCH_CMD", 4, 1, deadline) =~
             ~r/^\d\dS\d{4}0001DONE\d{3}$/

    assert {0, out} = library.(["list"])
    assert out =~ ~r/004711\.PRO  v1 of 1 .* cli .* on the machine: same$/m
    # and the transfer recorded in its history (issue 27)
    assert {0, out} = library.(["history", "004711.PRO"])

    assert out =~
             ~r/004711\.PRO v1  to machine  DOWNLOAD_GE\(004711\.PRO\) .* DONE  by WC string 0003 M0001$/m

    Acceptance.signal(proc, "TERM")
    status = Acceptance.await_exit(proc, 30_000)
    output = Acceptance.output(proc)
    assert [_, stop] = String.split(output, "SIGTERM received", parts: 2), output

    refute stop =~ ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry|\[error\]/,
           output

    refute output =~ ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry/, output
    assert status == 0, output

    # production logging: info, not debug, to the console and to VWS_LOG_DIR/vws-VWS1.log (named after its VWS_ID)
    refute output =~ "[debug]"
    log = File.read!(Path.join(log_dir, "vws-VWS1.log"))
    assert log =~ ~r/workstation=VWS1 partition=sun_comm \[info\] SUN_COMM listening for the WC/
    assert log =~ "SIGTERM received"
    refute log =~ "[debug]"
  end
end
