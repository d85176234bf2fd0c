defmodule Vws.Acceptance.ServeCycleTest do
  # The README's first hour: `mix vws.serve` in one terminal, the shipped machining cycle run
  # against it with `mix vws.wc --script` in another — real OS processes, the real WC TCP link.
  # Its floor starts as the demo's (a blank in tray #1, material handling), so the cycle ends
  # with exit status 0.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 420_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp serve do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "#{http}"] ++
          ["--time-scale", "20", "--robot-time-scale", "0.05"],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    %{proc: proc, wc: wc}
  end

  defp wc(wc, args) do
    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{wc}"] ++ args,
        env: [{"MIX_ENV", "dev"}]
      )

    status = Acceptance.await_exit(cli, 300_000)
    {status, Acceptance.output(cli)}
  end

  test "mix vws.wc --script priv/sims/machining_cycle.vws (then table1.vws, recover.vws) against mix vws.serve: exit status 0" do
    %{proc: proc, wc: port} = serve()
    assert Acceptance.output(proc) =~ "a blank in tray #1"

    {status, output} = wc(port, ["--script", "priv/sims/machining_cycle.vws"])
    assert status == 0, output
    assert output =~ ~r/result: +COMPLETED/, output
    assert output =~ ~r/steps done: +(\d+) of \1\b/, output

    # the part is back in tray #1: Table 1's script runs next, then the recovery script (which
    # finds nothing held), each to its end
    for script <- ["priv/sims/table1.vws", "priv/sims/recover.vws"] do
      {status, output} = wc(port, ["--script", script])
      assert status == 0, output
      assert output =~ ~r/result: +COMPLETED/, output
    end
  end
end
