defmodule Vws.Ops.WebTest do
  use ExUnit.Case, async: true

  alias Vws.Test.{JSONDecode, WCPeer, XMLLint}

  defp get(url, headers \\ []) do
    {:ok, {{_, status, _}, resp_headers, body}} =
      :httpc.request(:get, {String.to_charlist(url), headers}, [timeout: 30_000],
        body_format: :binary
      )

    {status, content_type(resp_headers), body}
  end

  defp post(url, headers) do
    {:ok, {{_, status, _}, _h, body}} =
      :httpc.request(
        :post,
        {String.to_charlist(url), headers, ~c"text/plain", ""},
        [timeout: 30_000],
        body_format: :binary
      )

    {status, JSONDecode.decode(body)}
  end

  defp content_type(headers) do
    case List.keyfind(headers, ~c"content-type", 0) do
      {_, v} -> to_string(v)
      nil -> nil
    end
  end

  defp web(opts) do
    pid = start_supervised!({Vws.Ops.Web, [port: 0] ++ opts}, id: make_ref())
    Vws.Ops.Web.url(pid)
  end

  setup do
    %{ws: ws, wc: wc} = Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot())
    %{ws: ws, wc: wc}
  end

  # (only where the host has an IPv6 loopback: a container may have none)
  @tag :ipv6
  test "an IPv6 address to bind: served there (the server opens its socket by the address's family)" do
    pid = start_supervised!({Vws.Ops.Web, [port: 0, bind: "::1"]}, id: make_ref())
    assert Vws.Ops.Web.url(pid) =~ ~r{^http://\[::1\]:\d+/$}

    {:ok, s} =
      :gen_tcp.connect({0, 0, 0, 0, 0, 0, 0, 1}, Vws.Ops.Web.port(pid), [
        :binary,
        :inet6,
        active: false
      ])

    :ok = :gen_tcp.send(s, "GET /api/state HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
    assert {:ok, "HTTP/1.1 200 OK\r\n" <> _} = :gen_tcp.recv(s, 0, 10_000)
    :gen_tcp.close(s)
  end

  test "binds 127.0.0.1 by default and serves the dashboard page" do
    url = web([])
    assert url =~ ~r{^http://127\.0\.0\.1:\d+/$}
    {200, "text/html; charset=utf-8", body} = get(url)
    assert body =~ "<title>VWS dashboard</title>"
    assert body =~ ~s(fetch("/api/state")
    assert body =~ "const POLL_MS = #{Vws.Ops.Web.Page.poll_ms()};"
    assert Vws.Ops.Web.Page.poll_ms() <= 500
  end

  test "/api/state: partitions, command statuses, devices, interlocks and the WC dialogue",
       %{ws: ws, wc: wc} do
    url = web([])
    :ok = Vws.CEC.Interlock.acquire(ws, :tray1, :robot, 1_000)
    {:ok, peer} = WCPeer.connect(wc)
    line = WCPeer.send_string(peer, 1, [{"R", 7, "HOLD AT TRAY"}])
    assert_receive {:executing, _pid, 7, _}, 5_000

    {200, "application/json", body} = get(url <> "api/state")
    state = JSONDecode.decode(body)
    assert state["control"] == false
    [me] = for w <- state["workstations"], w["id"] == ws, do: w

    robot = Enum.find(me["partitions"], &(&1["name"] == "ROBOT"))
    assert %{"number" => "0007", "status" => "EXECUTING", "state" => "running"} = robot
    assert robot["current"] == "0007 HOLD AT TRAY"

    assert Enum.map(me["partitions"], & &1["name"]) ==
             ~w(ROBOT MONARCH GRIPPER FIXTURE VACUUM HYDRAULIC)

    assert %{"name" => "VISE", "value" => "NO DATA (NO LINK TO DAQ #1)"} =
             Enum.find(me["devices"], &(&1["location"] == 3))

    assert [%{"what" => "tray1", "holder" => "robot", "reasons" => "lease", "age_ms" => age}] =
             me["interlocks"]

    assert is_integer(age)

    # a device status is words, never an Elixir term: location 11 holds {:no_data, why}
    assert %{"name" => "SENSORS", "value" => "NO DATA (NO LINK TO DAQ #1)", "no_data" => true} =
             Enum.find(me["devices"], &(&1["location"] == 11))

    assert me["sensors"]["note"] == "NO DATA (NO LINK TO DAQ #1)"
    refute body =~ ~r/[{}]:|%\{|#PID|\{:/
    assert me["wc"]["state"] == "connected"

    assert %{"dir" => "in", "line" => String.trim_trailing(line)} in Enum.map(
             me["wc"]["dialogue"],
             &Map.take(&1, ["dir", "line"])
           )
  end

  test "read-only without a token: control actions are refused 403", %{ws: ws} do
    url = web([])

    assert {403, %{"error" => "read-only: no control token configured"}} =
             post(url <> "api/status?ws=#{ws}&name=VISE", [{~c"x-vws-token", ~c"anything"}])
  end

  test "with a token: a control action needs it", %{ws: ws} do
    url = web(token: "s3cret")
    {200, _, body} = get(url <> "api/state")
    assert JSONDecode.decode(body)["control"] == true

    q = url <> "api/status?ws=#{ws}&name=ROBOT_CMD"
    assert {403, _} = post(q, [])
    assert {403, _} = post(q, [{~c"x-vws-token", ~c"s3cre"}])
    assert {403, _} = post(q, [{~c"x-vws-token", ~c"s3cret!"}])
    assert {200, %{"answer" => "0000NONE"}} = post(q, [{~c"x-vws-token", ~c"s3cret"}])
    assert {404, _} = post(url <> "api/status?ws=nope&name=VISE", [{~c"x-vws-token", ~c"s3cret"}])
  end

  @tag :mtconnect_schemas
  test "the MTConnect agent answers on the same server, and its documents validate", %{ws: ws} do
    url = web(workstations: fn -> [ws] end)

    {200, "application/xml", body} = get(url <> "probe")
    assert XMLLint.validate!(body, :devices) =~ ~s(name="#{ws}")

    {200, "application/xml", body} = get(url <> "current")
    XMLLint.validate!(body, :streams)

    {200, "application/xml", body} = get(url <> "#{ws}/current")
    XMLLint.validate!(body, :streams)

    {200, "application/xml", body} = get(url <> "sample?from=1&count=3")
    assert length(Regex.scan(~r/ sequence="\d+"/, XMLLint.validate!(body, :streams))) == 3

    {400, "application/xml", body} = get(url <> "sample?from=0")
    assert XMLLint.validate!(body, :error) =~ ~s(errorCode="OUT_OF_RANGE")

    {400, "application/xml", body} = get(url <> "sample?from=99999999")
    assert XMLLint.validate!(body, :error) =~ ~s(errorCode="OUT_OF_RANGE")

    {400, "application/xml", body} = get(url <> "sample?count=many")
    assert XMLLint.validate!(body, :error) =~ ~s(errorCode="INVALID_REQUEST")

    {404, "application/xml", body} = get(url <> "NOPE/probe")
    assert XMLLint.validate!(body, :error) =~ ~s(errorCode="NO_DEVICE")
  end

  test "HTTP work yields to the workstations: the listener's socket work runs in its (low-priority) processes" do
    pid = start_supervised!({Vws.Ops.Web, [port: 0]}, id: make_ref())

    children =
      Map.new(Supervisor.which_children(pid), fn {_id, child, _, [module]} -> {module, child} end)

    server = children[Vws.Ops.Web.Server]
    %{socket: socket, acceptors: acceptors, clients: clients} = :sys.get_state(server)

    # OTP's :socket (NIFs called by these processes alone) rather than inet_drv (port tasks,
    # scheduled beside every process) or gen_tcp's socket backend (a gen_tcp_socket server per
    # socket, at normal priority): see bench/http_hostile.exs
    assert {:"$socket", _} = socket

    low = [children[Vws.Ops.MTConnect.Agent], children[Vws.Ops.Web.Snapshot], clients | acceptors]

    for p <- [children[Task.Supervisor] | low] do
      assert Process.info(p, :priority) == {:priority, :low}
    end

    {200, _, _} = get(Vws.Ops.Web.url(pid) <> "api/state")
  end

  test "unknown paths are 404, other methods 405" do
    url = web([])
    assert {404, _, _} = get(url <> "nothing/here/at/all")

    {:ok, {{_, 405, _}, _, _}} =
      :httpc.request(:put, {String.to_charlist(url), [], ~c"text/plain", "x"}, [], [])
  end

  test "a port in use is reported, not hidden" do
    url = web([])
    [_, port] = Regex.run(~r/:(\d+)\/$/, url)
    assert {:error, message} = Vws.Ops.Web.start_from_cli(http_port: String.to_integer(port))
    # in words, naming the port: no Elixir term
    assert message =~ "HTTP port #{port} is in use (127.0.0.1:#{port})"
    refute message =~ ~r/[{}]/
  end
end
