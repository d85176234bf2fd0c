defmodule Vws.Acceptance.GuaranteesTest do
  # Issue 24's black-box checks, against `mix vws.serve` as the README runs it: a real OS process
  # with its simulated floor, driven over the real WC TCP link by the integrator's command line.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp serve(extra \\ []) do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "#{http}"] ++ extra,
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    %{proc: proc, wc: wc, http: http}
  end

  defp wc(port, args, timeout \\ 120_000) do
    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{port}"] ++ args,
        env: [{"MIX_ENV", "dev"}]
      )

    {Acceptance.await_exit(cli, timeout), Acceptance.output(cli)}
  end

  test "DRIP_FEED with the robot inside the machine ends ERROR INTERLOCK and the machine runs nothing",
       %{tmp_dir: tmp} do
    %{wc: port} = serve(["--time-scale", "20"])
    File.cp!("priv/sims/programs/001234.nc", Path.join(tmp, "001234.nc"))

    script = Path.join(tmp, "arm_inside.vws")

    File.write!(script, """
    R DISABLE_TABLE
    R DO APPRO VISE/50
    R DO MOVES VISE
    DOWNLOAD 001234.nc
    M DRIP_FEED
    """)

    {status, output} = wc(port, ["--script", script])
    assert status != 0, output
    assert output =~ "MONARCH command 0002 ended ERROR INTERLOCK TABLE HELD BY ROBOT", output

    # the machine ran nothing: MONARCH idle, and CYCLE_START is refused the same way
    {0, monarch} = wc(port, ["--status", "MONARCH"])
    assert monarch =~ "IDLE", monarch
    {_, cycle} = wc(port, ["--command", "M CYCLE_START"])
    assert cycle =~ ~r/M\d{4} CYCLE_START: ERROR INTERLOCK TABLE HELD BY ROBOT/, cycle
  end
end
