defmodule Vws.Acceptance.ServeRS232Test do
  # `mix vws.serve --dnc-profile rs232-xonxoff` as a user runs it: a real OS process whose
  # machine tool is a simulated plain RS-232 control under XON/XOFF, driven by `mix vws.wc`.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  test "DOWNLOAD_GE and DRIP_FEED to a plain RS-232 control; what it cannot do ends ERROR in words",
       ctx do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.serve(
        ["--wc-port", "#{wc}", "--http-port", "#{http}", "--no-journal"] ++
          ["--no-library", "--dnc-profile", "rs232-xonxoff"],
        [env: [{"MIX_ENV", "dev"}]],
        90_000
      )

    assert Acceptance.output(proc) =~ ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/
    assert Acceptance.output(proc) =~ ~r/Simulated RS-232 control \(XON\/XOFF\) on tcp:/
    assert Acceptance.output(proc) =~ "(profile rs232-xonxoff)"

    File.cp!(
      Path.join(Acceptance.root(), "priv/sims/programs/001234.nc"),
      "#{ctx.tmp_dir}/001234.nc"
    )

    script = Path.join(ctx.tmp_dir, "rs232.vws")

    File.write!(script, """
    TIMEOUT 120
    DOWNLOAD 001234.nc
    M DOWNLOAD_GE
    M DRIP_FEED
    """)

    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{wc}", "--script", script],
        env: [{"MIX_ENV", "dev"}]
      )

    assert Acceptance.await_exit(cli, 180_000) == 0, Acceptance.output(cli)
    # (0001 was DOWNLOAD_HP) DOWNLOAD_GE read back by the control, then the drip feed
    assert Acceptance.output(cli) =~ "MONARCH 0002 DONE"
    assert Acceptance.output(cli) =~ "MONARCH 0003 DONE"

    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{wc}", "--command", "M STATUS"],
        env: [{"MIX_ENV", "dev"}]
      )

    assert Acceptance.await_exit(cli, 60_000) != 0
    assert Acceptance.output(cli) =~ "ERROR NO STATUS REPORT FROM AN RS-232 CONTROL"
  end

  test "an unknown profile stops it before anything starts, in words" do
    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "0", "--http-port", "0", "--no-journal"] ++
          ["--no-library", "--dnc-profile", "fanuc-dnc2"],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    assert Acceptance.await_exit(proc, 90_000) != 0

    assert Acceptance.output(proc) =~
             ~s|--dnc-profile: unknown DNC port profile "fanuc-dnc2" (known: ge2000-level2, rs232-xonxoff)|
  end
end
