defmodule Vws.Acceptance.MonitoringTest do
  # Issue 25's black-box check of monitoring while the machine runs a program, against
  # `mix vws.serve` as the README runs it: a drip-fed program sent by the integrator's command
  # line over the WC link, watched through the MTConnect agent over real HTTP meanwhile.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  test "while a drip-fed program runs, MTConnect's Execution is ACTIVE and Program names it; MONARCH says ACTIVE",
       %{tmp_dir: tmp} do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    serve =
      Acceptance.start(["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "#{http}"],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(serve) end)
    Acceptance.await(serve, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    Acceptance.await(serve, ~r/Dashboard and MTConnect agent: http:\/\/127\.0\.0\.1:#{http}\//)

    # about 14 KB, the simulated GE-2000's memory 8 KB: it runs at 400 characters a second while
    # it arrives, pausing the CEC with WACKs for about 15 s, and is still running (its buffer
    # draining) when DRIP_FEED ends DONE
    lines = ["%", "O4711"] ++ for(i <- 1..700, do: "N#{i} G01 X#{i}.5 F300") ++ ["M30", "%"]
    File.write!(Path.join(tmp, "004711.nc"), Enum.join(lines, "\n") <> "\n")
    script = Path.join(tmp, "drip.vws")

    File.write!(script, """
    TIMEOUT 120
    DOWNLOAD 004711.nc
    M DRIP_FEED
    EXPECT MONARCH ACTIVE
    """)

    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{wc}", "--script", script],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(cli) end)
    samples = watch(http, cli, [])
    assert Acceptance.await_exit(cli, 5_000) == 0, Acceptance.output(cli)

    # every sample taken while the feed was under way: ACTIVE, running 004711
    feeding =
      for %{transfer: t} = s <- samples,
          [_, done, total] <- [Regex.run(~r/^DRIP FEED 004711\.PRO (\d+)\/(\d+) BYTES/, t)],
          String.to_integer(done) < String.to_integer(total),
          do: s

    assert length(feeding) >= 3, inspect(Enum.take(samples, -20), pretty: true)

    for s <- feeding do
      assert s.execution == "ACTIVE", inspect(s)
      assert s.program == "004711", inspect(s)
    end
  end

  # /current every 250 ms until the WC's script has ended: Execution, Program, the transfer.
  defp watch(http, cli, acc) do
    acc =
      case Acceptance.http_get(http, "/current") do
        {200, xml} ->
          [
            %{
              execution: item(xml, "vmc_path_exec"),
              program: item(xml, "vmc_path_program"),
              transfer: item(xml, "vmc_path_transfer")
            }
            | acc
          ]

        _ ->
          acc
      end

    if GenServer.call(cli, :state).status == nil do
      Process.sleep(250)
      watch(http, cli, acc)
    else
      Enum.reverse(acc)
    end
  end

  defp item(xml, id) do
    case Regex.run(~r/dataItemId="[^"]*#{id}"[^>]*>([^<]*)</, xml) do
      [_, value] -> value
      nil -> nil
    end
  end
end
