defmodule Vws.Ops.HealthTest do
  # Vws.Ops.Health: healthy only while each expected workstation runs and its links are up or
  # down for less than the grace; /health answers it without a token and tells the reasons only
  # to a reader.
  use ExUnit.Case, async: true

  import Vws.Test.Eventually

  alias Vws.Ops.Health
  alias Vws.Ops.Web.Handler

  # a TCP port nothing listens on: the GE-2000 link dials it again and again
  defp dead_port do
    {:ok, socket} = :gen_tcp.listen(0, ip: {127, 0, 0, 1})
    {:ok, port} = :inet.port(socket)
    :gen_tcp.close(socket)
    port
  end

  defp health(grace_ms) do
    name = :"health_test_#{System.unique_integer([:positive])}"
    start_supervised!({Health, name: name, grace_ms: grace_ms}, id: name)
    name
  end

  test "a workstation whose GE-2000 link stays down is failing once the grace is over, with the link named" do
    %{ws: ws} =
      Vws.Test.Workstation.start(
        wc: "tcp://127.0.0.1:0",
        devices: [ge2000: "tcp://127.0.0.1:#{dead_port()}"]
      )

    patient = health(600_000)
    strict = health(0)
    :ok = Health.expect(patient, ws)
    :ok = Health.expect(strict, ws)

    # within its back-off the link is reconnecting: healthy
    assert Health.check(patient) == :ok

    # past the grace it is a reason, in words
    assert eventually(fn -> Health.check(strict) != :ok end, 10_000)
    assert {:failing, [reason]} = Health.check(strict)
    assert reason =~ ~r/^#{ws}: GE-2000 DNC link down for \d+ s$/

    # a workstation that is not running is failing, whatever the grace
    # (as soon as its registry entry is gone: the registry hears of the stop a moment later)
    :ok = stop_supervised({Vws.CEC.Workstation, ws})

    assert eventually(
             fn -> Health.check(patient) == {:failing, ["#{ws} is not running"]} end,
             10_000
           )

    # forgotten (stopped on purpose): healthy again
    :ok = Health.forget(patient, ws)
    assert Health.check(patient) == :ok
  end

  test "links up and the WC port listening: healthy even with no grace" do
    sim = start_supervised!({Vws.Sim.GE2000, []})

    %{ws: ws} =
      Vws.Test.Workstation.start(
        wc: "tcp://127.0.0.1:0",
        devices: [ge2000: Vws.Sim.GE2000.endpoint(sim)]
      )

    strict = health(0)
    :ok = Health.expect(strict, ws)
    assert eventually(fn -> Health.check(strict) == :ok end, 10_000)
    assert Health.expected(strict) == [ws]
  end

  test "GET /health needs no token; with a read token set, only a reader is told why it fails" do
    settings = %{token: "control-secret", read_token: "read-secret", snapshot: nil, agent: nil}
    request = %{method: "GET", path: "/health", query: %{}, headers: %{}, body: ""}

    assert Handler.authorize(request, settings) == :ok
    # the other reads still need the read token
    assert {:deny, {401, _, _, _}} = Handler.authorize(%{request | path: "/api/state"}, settings)

    # the node's own health (no workstation expected in the test node): ok
    assert {200, "application/json", body} = Handler.handle(request, settings)
    assert IO.iodata_to_binary(body) == ~s({"status":"ok"})

    # the reasons, when failing, only with the read token
    assert {503, ~s({"status":"failing"})} = answer_failing(false)
    {503, body} = answer_failing(true)
    assert IO.iodata_to_binary(body) =~ ~s("reasons":[")
  end

  defp answer_failing(reasons?) do
    name = health(0)
    :ok = Health.expect(name, "health-test-absent-#{System.unique_integer([:positive])}")
    {:failing, reasons} = Health.check(name)
    {status, body} = Health.answer(reasons?, {:failing, reasons})
    {status, IO.iodata_to_binary(body)}
  end

  test "bin/vws health's probe: no node answering is failing, in one line" do
    assert {1, line} = Health.probe(%{"VWS_HTTP_PORT" => "#{dead_port()}"})
    assert line =~ ~r"^failing: no node answers at http://127\.0\.0\.1:\d+/health$"
    assert {1, "failing: VWS_HTTP_PORT is off" <> _} = Health.probe(%{"VWS_HTTP_PORT" => "off"})
  end
end
