defmodule Vws.Acceptance.DashboardActionsTest do
  # The dashboard's operator commands as a person uses them: `mix vws.serve` with a control token
  # (a real OS process, the whole simulated floor), a program stored by a WC's DOWNLOAD_HP, leases
  # left held by WC commands, and every action sent from the page in a real headless Chromium —
  # the form filled and sent by the page's own script (the link's #token=…&set=…&text=… fragment,
  # as a click on Send) — then followed on the page until it ends DONE or ERROR. The WC stays
  # connected on its link throughout: the actions never take it over.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance
  alias Vws.Peers.WC.Client
  alias Vws.Codecs.WC.Reply

  @moduletag :acceptance
  @moduletag timeout: 600_000
  @chromium Vws.Test.Browser.chromium()
  if !@chromium do
    @moduletag skip: "chromium is not installed (apt-get install -y chromium)"
  end

  @token "dashboard-actions-test-token"

  setup_all do
    :ok = Acceptance.prebuild("dev")
  end

  setup do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.start(
        ~w(mix vws.serve --wc-port #{wc} --http-port #{http} --time-scale 10 --ge2000-baud 9600),
        env: [{"MIX_ENV", "dev"}, {"VWS_HTTP_TOKEN", @token}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    [_, url] = Acceptance.await(proc, ~r{Dashboard and MTConnect agent: (http://\S+)}, 120_000)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC/, 30_000)
    %{proc: proc, wc: wc, url: url}
  end

  test "send, compare, receive, drip-feed and release, each from the page through SUN_COMM",
       %{proc: proc, wc: wc, url: url} do
    # a healthy idle floor: nothing red (not read yet is not an error); without the token typed,
    # the page offers no action
    dom = page(url)
    page = text(dom)
    assert page =~ "no errors seen"
    assert page =~ ~r/NO DATA \((GE-2000|VAL II) NOT READ YET\)/
    refute dom =~ ~r/class="[^"]*\berror\b/
    assert dom =~ ~r/<div id="actions" hidden/
    assert page =~ "Recent events"

    # a program into the library, as a WC stores one (DOWNLOAD_HP)
    socket = connect(wc)

    program =
      ["%", "O1234", "G21 G17 G90 G54", "T1 M6", "S1200 M3", "M8"] ++
        for(i <- 1..20, do: "N#{i} G01 X#{i}.0 Y0 F100") ++ ["M9", "M30", "%"]

    assert "05A0001" <> _ = request(socket, Acceptance.wc_frame("*0001*M0001DOWNLOAD_HP*"))

    for {line, n} <- Enum.with_index(program, 1), do: request(socket, nc_line(n, line))
    :gen_tcp.close(socket)

    {:ok, client} =
      Client.connect("tcp://127.0.0.1:#{wc}", sequence: 10, numbers: %{"M" => 2, "R" => 1})

    assert :done = Client.await_command(client, "M", 1, 10_000)

    # each library action ends DONE on the page
    assert "DONE" = action(url, "M", "DOWNLOAD_GE(001234.PRO/1)")
    assert "DONE" = action(url, "M", "COMPARE_GE(001234.PRO)")
    assert "DONE" = action(url, "M", "UPLOAD_GE(001234.PRO)")
    assert "DONE" = action(url, "M", "DRIP_FEED")

    # the library's program restarted at line 16 (N10) from the page (issue 27): the preamble
    # restoring the modal state of lines 1-15 is shown on the page, and was told before it went
    assert "DONE" = action(url, "M", "DRIP_FEED(001234.PRO/1/N16)")
    page = text(page(url))
    assert page =~ "Drip-feed restart (MONARCH)"
    assert page =~ ~r/001234.PRO version 1 restarted at line 16 .* UTC — restored preamble/

    assert page =~
             ~r/sent before line 16:\s+G21 G17 G90 G54\s+T1 M6\s+S1200 M3\s+M8\s+G01 F100\s/

    assert page =~
             "MONARCH: DRIP_FEED of 001234.PRO version 1 restarts at line 16, restored preamble: " <>
               "G21 G17 G90 G54 / T1 M6 / S1200 M3 / M8 / G01 F100"

    # past the end: refused in words on the page, nothing sent
    assert action(url, "M", "DRIP_FEED(001234.PRO/N99)") ==
             "ERROR RESTART LINE 99 BEYOND THE END (LAST BLOCK 28)"

    # MONARCH keeps the table after its program: released from the page
    assert text(page(url)) =~ ~r/table monarch/
    assert "DONE" = action(url, "M", "RELEASE_TABLE")
    refute text(page(url)) =~ ~r/table monarch/

    # leases a failed cycle would leave: taken by the WC's commands, released from the page
    run(client, "R", "DISABLE_TRAY1")
    run(client, "R", "DISABLE_TABLE")
    page = text(page(url))
    assert page =~ ~r/tray1 robot disabled/
    assert page =~ ~r/table robot disabled/

    assert "DONE" = action(url, "R", "RELEASE_TRAY1")
    assert "DONE" = action(url, "R", "RELEASE_TABLE")
    page = text(page(url))
    refute page =~ ~r/tray1 robot disabled/
    refute page =~ ~r/table robot disabled/

    run(client, "F", "DISABLE_TABLE")
    assert text(page(url)) =~ ~r/table fixture disabled/
    assert "DONE" = action(url, "F", "RELEASE_TABLE")
    refute text(page(url)) =~ ~r/table fixture disabled/

    # the same path as a WC's command: MONARCH busy with the WC's DOWNLOAD_HP (held open half-way)
    # refuses the page's command as it would a WC's
    Client.close(client)
    socket = connect(wc)
    assert "05A0050" <> _ = request(socket, Acceptance.wc_frame("*0050*M0050DOWNLOAD_HP*"))
    request(socket, nc_line(1, "%"))
    assert action(url, "M", "COMPARE_GE(001234.PRO)") =~ ~r/^ERROR BUSY 0050$/

    # the WC's download goes on to its end: the closing line answered with the lines stored
    answers =
      for {line, n} <- Enum.with_index(tl(program), 2), do: request(socket, nc_line(n, line))

    total = length(program)
    # (A count, or A count/CRC since the whole-program check)
    assert {:ok, ack} = Reply.decode(List.last(answers))
    assert elem(ack, 0) == :line_ack and elem(ack, 1) == total
    :gen_tcp.close(socket)

    # not an operator command: refused by the server, nothing runs
    dom = page(url <> "#token=#{@token}&set=R&text=DO%20MOVE%20NOWHERE")
    assert text(dom) =~ "refused: not an operator command: R DO MOVE NOWHERE"

    # a wrong token: refused
    dom = page(url <> "#token=wrong&set=M&text=DRIP_FEED")
    assert text(dom) =~ "refused: control needs the right x-vws-token"

    # after a reload the node's history still has the page's commands, with the node's time
    page = text(page(url))
    assert page =~ ~r/\d\d:\d\d:\d\d\.\d{3}\s+OPERATOR: R9\d{3} RELEASE_TRAY1 sent/
    assert page =~ ~r/\d\d:\d\d:\d\d\.\d{3}\s+MONARCH: 9\d{3} DONE/

    refute Acceptance.output(proc) =~ "FunctionClauseError"
  end

  # Sends one action from the page and follows it there: the page's answer line, which the page
  # itself keeps following (from its polls of the node's state) until the command ends.
  defp action(url, set, text) do
    fragment = "#token=#{@token}&set=#{set}&text=#{URI.encode_www_form(text)}"

    ended = ~S"""
    /: (DONE|ERROR)|^refused|status location now/.test((document.getElementById('command-status') || {}).textContent || '')
    """

    dom = page(url <> fragment, until: ended, timeout: 90_000)

    assert [_, line] = Regex.run(~r/<span[^>]*id="command-status"[^>]*>([^<]*)</, dom),
           "no answer for #{set} #{text}: #{Regex.run(~r/id="command-answer".{0,400}/s, dom)}"

    re = ~r/^#{set}9\d{3} #{Regex.escape(text)}: (DONE|ERROR[A-Z0-9 #.,()\/-]*)$/

    case Regex.run(re, text(line)) do
      [_, status] -> status
      nil -> flunk("no end for #{set} #{text}: #{line}")
    end
  end

  defp run(client, letter, text, timeout \\ 30_000) do
    {:ok, [{^letter, n}]} = Client.send_commands(client, [{letter, text}])
    assert :done = Client.await_command(client, letter, n, timeout), "#{letter} #{text}"
  end

  defp connect(port) do
    {:ok, socket} =
      :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, packet: :line], 5_000)

    socket
  end

  defp request(socket, bytes) do
    bytes = if String.ends_with?(bytes, "\r\n"), do: bytes, else: bytes <> "\r\n"
    :ok = :gen_tcp.send(socket, bytes)
    {:ok, line} = :gen_tcp.recv(socket, 0, 10_000)
    String.trim_trailing(line)
  end

  defp nc_line(n, text), do: IO.iodata_to_binary(Reply.encode({:line, n, text}))

  defdelegate page(url, opts \\ []), to: Vws.Test.Browser
  defdelegate text(dom), to: Vws.Test.Browser
end
