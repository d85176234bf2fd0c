defmodule Vws.Acceptance.ServeWordsTest do
  # `mix vws.serve` refusing what it cannot do, in words (issue 25): a bad flag and a WC port in
  # use are each one line naming the flag or the port, exit status 1, no stack trace and no
  # Elixir term.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 180_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  @stack ~r/\*\* \((exit|EXIT|RuntimeError|MatchError)|\(stdlib|\(vws 0|\{"--|\{:/

  defp serve(args) do
    proc = Acceptance.start(["mix", "vws.serve" | args], env: [{"MIX_ENV", "dev"}])
    on_exit(fn -> Acceptance.stop(proc) end)
    status = Acceptance.await_exit(proc, 90_000)
    {status, Acceptance.output(proc)}
  end

  test "--wc-port abc: one line naming the flag and what is wrong" do
    {status, out} = serve(["--wc-port", "abc"])
    assert status == 1, out
    assert out =~ "** (Mix) --wc-port: abc is not a port number (0-65535; 0 picks a free one)"
    refute out =~ "unknown options", out
    refute out =~ @stack, out
  end

  test "a WC port in use: one line naming the port, nothing started" do
    {:ok, socket} = :gen_tcp.listen(0, ip: {127, 0, 0, 1})
    {:ok, port} = :inet.port(socket)
    on_exit(fn -> :gen_tcp.close(socket) end)

    {status, out} = serve(["--wc-port", "#{port}", "--http-port", "0"])
    assert status == 1, out

    assert out =~
             "** (Mix) workstation VWS did not start: WC port #{port} is in use (tcp://127.0.0.1:#{port})",
           out

    refute out =~ @stack, out
    refute out =~ "SUN_COMM waits for the WC", out
  end
end
