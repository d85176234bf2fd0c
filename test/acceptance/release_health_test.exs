defmodule Vws.Acceptance.ReleaseHealthTest do
  # A release that cannot do its job says so and stops, and one that can says so when asked:
  #
  #   * a configured workstation that cannot start (VWS_WC on 0.0.0.0 without an allow-list),
  #     a configuration value it cannot use (VWS_BCC=crc): exit status 1, one line saying why,
  #     no stack trace, no erl_crash.dump in the working directory — systemd's
  #     Restart=on-failure sees it, an operator reads it;
  #   * a running one: GET /health 200 {"status":"ok"} (no token needed) and `bin/vws health`
  #     exit status 0; once it has stopped, `bin/vws health` says no node answers, status 1.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :release
  @moduletag timeout: 300_000

  setup_all do
    %{release: Acceptance.release()}
  end

  defp env(tmp, extra) do
    [
      {"VWS_ID", "VWS1"},
      {"VWS_DATA_DIR", Path.join(tmp, "data")},
      {"VWS_LOG_DIR", "off"},
      {"RELEASE_TMP", Path.join(tmp, "rel-tmp")},
      {"RELEASE_DISTRIBUTION", "none"}
    ] ++ extra
  end

  defp start(release, tmp, extra) do
    proc =
      Acceptance.start([Path.join(release, "bin/vws"), "start"], env: env(tmp, extra), cd: tmp)

    on_exit(fn -> Acceptance.stop(proc) end)
    proc
  end

  @stack ~r/\*\* \(|\(stdlib|\(elixir|init terminating|Crash dump|erl_crash/

  @tag :tmp_dir
  test "a workstation that cannot start, a port in use, a value that cannot be used: status 1, one line, no crash dump",
       %{release: release, tmp_dir: tmp} do
    http = Acceptance.free_port()

    # VWS_WC on every interface, and no VWS_WC_ALLOW to say who may connect
    proc =
      start(release, tmp, [
        {"VWS_WC", "tcp://0.0.0.0:#{Acceptance.free_port()}"},
        {"VWS_HTTP_PORT", "#{http}"}
      ])

    assert Acceptance.await_exit(proc, 60_000) == 1, Acceptance.output(proc)
    out = Acceptance.output(proc)

    assert [line] = Regex.run(~r/^.*\[error\] workstation VWS1 cannot start: .*$/m, out),
           out

    assert line =~ "is not a loopback address"
    assert line =~ "VWS_WC_ALLOW"
    # the one error line: nothing was started to fail on its own
    assert length(Regex.scan(~r/\[error\]/, out)) == 1, out
    refute out =~ @stack, out
    refute out =~ "{:", out
    refute File.exists?(Path.join(tmp, "erl_crash.dump"))

    # the dashboard's port in use
    {:ok, socket} = :gen_tcp.listen(0, ip: {127, 0, 0, 1})
    {:ok, taken} = :inet.port(socket)
    on_exit(fn -> :gen_tcp.close(socket) end)

    proc =
      start(release, tmp, [
        {"VWS_WC", "tcp://127.0.0.1:#{Acceptance.free_port()}"},
        {"VWS_HTTP_PORT", "#{taken}"}
      ])

    assert Acceptance.await_exit(proc, 60_000) == 1, Acceptance.output(proc)
    out = Acceptance.output(proc)

    assert out =~
             "[error] the dashboard cannot start: HTTP port #{taken} is in use (127.0.0.1:#{taken}) (VWS_HTTP_PORT)",
           out

    refute out =~ @stack, out
    refute File.exists?(Path.join(tmp, "erl_crash.dump"))

    # a configuration value the release cannot use: one line from config/runtime.exs
    proc =
      start(release, tmp, [
        {"VWS_WC", "tcp://127.0.0.1:#{Acceptance.free_port()}"},
        {"VWS_BCC", "crc"}
      ])

    assert Acceptance.await_exit(proc, 60_000) == 1, Acceptance.output(proc)
    out = Acceptance.output(proc)
    assert String.trim(out) == "ERROR: VWS_BCC must be sum or xor, not crc", out
    refute File.exists?(Path.join(tmp, "erl_crash.dump"))
  end

  @tag :tmp_dir
  test "a running release: GET /health 200 without a token, bin/vws health 0; stopped: bin/vws health 1",
       %{release: release, tmp_dir: tmp} do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      start(release, tmp, [
        {"VWS_WC", "tcp://127.0.0.1:#{wc}"},
        {"VWS_HTTP_PORT", "#{http}"},
        {"VWS_HTTP_READ_TOKEN", "read-secret"}
      ])

    Acceptance.await(
      proc,
      ~r/SUN_COMM listening for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/,
      60_000
    )

    # the web server starts after the workstations: on a loaded host the first GET came before it
    Acceptance.await(proc, ~r/VWS web server on http:\/\/127\.0\.0\.1:#{http}\//, 60_000)

    # every other read needs the read token; /health does not, and says nothing more than this
    assert {401, _} = Acceptance.http_get(http, "/api/state")
    assert {200, ~s({"status":"ok"})} = Acceptance.http_get(http, "/health")

    health = fn ->
      p =
        Acceptance.start([Path.join(release, "bin/vws"), "health"],
          env: env(tmp, [{"VWS_HTTP_PORT", "#{http}"}]),
          cd: tmp
        )

      {Acceptance.await_exit(p, 60_000), String.trim(Acceptance.output(p))}
    end

    assert health.() == {0, "ok"}

    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 30_000) == 0, Acceptance.output(proc)

    assert health.() ==
             {1, "failing: no node answers at http://127.0.0.1:#{http}/health"}
  end
end
