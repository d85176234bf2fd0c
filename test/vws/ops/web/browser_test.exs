defmodule Vws.Ops.Web.BrowserTest do
  # The dashboard as a person sees it: a real headless Chromium loads the page, its JavaScript
  # polls /api/state, and the test reads the DOM Chromium renders.
  use ExUnit.Case, async: true

  alias Vws.Test.WCPeer

  @moduletag :browser
  @chromium Vws.Test.Browser.chromium()
  if !@chromium do
    @moduletag skip: "chromium is not installed (apt-get install -y chromium)"
  end

  @moduletag timeout: 120_000

  defdelegate dump_dom(url, budget_ms), to: Vws.Test.Browser
  defdelegate text(dom), to: Vws.Test.Browser

  defp row(text, first_cell),
    do: Regex.run(~r/#{first_cell} [^\n]*/, text) |> List.wrap() |> List.first()

  setup do
    %{ws: ws, wc: wc} = Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot())
    web = start_supervised!({Vws.Ops.Web, port: 0}, id: make_ref())
    %{ws: ws, wc: wc, url: Vws.Ops.Web.url(web), port: Vws.Ops.Web.port(web)}
  end

  test "shows the partitions, a command the WC sent, device statuses and the WC dialogue, updating live",
       %{ws: ws, wc: wc, url: url, port: port} do
    {:ok, peer} = WCPeer.connect(wc)
    WCPeer.send_string(peer, 1, [{"R", 7, "HOLD AT TRAY 1"}, {"G", 8, "OPEN"}])
    assert "05A0001" <> _ = WCPeer.recv_line(peer)
    assert_receive {:executing, robot_cmd, 7, _}, 5_000
    :ok = Vws.CEC.Interlock.acquire(ws, :table, :robot, 1_000)

    # While Chromium runs, the robot's command finishes as soon as the page has fetched the state
    # showing it EXECUTING (released from this server's request event, so no timing luck is
    # involved); the page must then show DONE without being reloaded.
    test_pid = self()
    handler = {__MODULE__, make_ref()}

    Vws.Telemetry.attach(
      handler,
      [:vws, :web, :request],
      fn
        _, _, %{path: "/api/state", status: 200, port: ^port}, {pid, command} ->
          send(command, {:result, :done})
          send(pid, :page_polled)

        _, _, _, _ ->
          :ok
      end,
      {test_pid, robot_cmd}
    )

    on_exit(fn -> Vws.Telemetry.detach(handler) end)

    browser = Task.async(fn -> dump_dom(url, 6_000) end)
    assert_receive :page_polled, 30_000
    dom = Task.await(browser, 60_000)
    page = text(dom)

    assert page =~ "Workstation #{ws}"

    for name <- ~w(ROBOT MONARCH GRIPPER FIXTURE VACUUM HYDRAULIC) do
      assert page =~ ~r/\b#{name}\b/
    end

    # the command the test caused: EXECUTING when the page first drew it, then DONE, live
    assert row(page, "ROBOT") =~ ~r/ROBOT idle 0007 DONE/
    # the node's history, each event with the node's time of the write
    assert page =~
             ~r/\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3}\s+ROBOT: 0007 EXECUTING HOLD AT TRAY 1/

    assert page =~ ~r/\d\d:\d\d:\d\d\.\d{3}\s+ROBOT: 0007 DONE/
    assert row(page, "GRIPPER") =~ "0008 ERROR NO LINK TO DAQ #1"

    # device status, interlocks, links
    assert page =~ ~r/3 VISE NO DATA \(NO LINK TO DAQ #1\)/
    assert page =~ ~r/table robot/
    assert page =~ ~r/WC \(SUN_COMM\) connected 0/
    # and the error it ended with, highlighted
    assert dom =~ ~r/<div class="error new">[^<]*GRIPPER: 0008 ERROR NO LINK TO DAQ #1/

    # the WC dialogue, both ways
    assert page =~ ~r/WC → CEC \*0001\*R0007HOLD AT TRAY 1\*G0008OPEN\*\d{3}/
    assert page =~ ~r/CEC → WC 05A0001\d{3}/

    # it polled at least twice a second of page time (6 s here)
    [_, updates] = Regex.run(~r/updates: (\d+)/, page)
    assert String.to_integer(updates) >= 12

    # read-only: no control form shown
    assert dom =~ ~r/<section class="ws" id="control" hidden/
  end

  test "with a control token the page offers the status-query form", %{ws: ws} do
    web = start_supervised!({Vws.Ops.Web, port: 0, token: "t"}, id: make_ref())
    dom = dump_dom(Vws.Ops.Web.url(web), 1_000)
    # shown (not hidden), with this workstation to choose
    assert dom =~ ~r/<section class="ws" id="control">/
    assert dom =~ ~s(<option value="#{ws}">#{ws}</option>)
  end
end
