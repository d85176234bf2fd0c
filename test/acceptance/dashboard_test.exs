defmodule Vws.Acceptance.DashboardTest do
  # The dashboard as a person uses it: `mix vws.serve` started as the README says (a real OS
  # process with the whole simulated floor), commands sent over the real WC TCP link, and the
  # page read by a real headless Chromium after its scripts ran — the DOM checked, a screenshot
  # kept (_build/acceptance/dashboard*.png) for a person to look at.
  # async: with the suite's longest-first order (Vws.Test.ModuleOrder) it starts at once, beside
  # other long modules, rather than alone in the sync phase
  use ExUnit.Case, async: true

  import Vws.Codecs.WC.Command, only: [pad4: 1]

  alias Vws.Test.Acceptance
  alias Vws.Peers.WC.Client
  alias Vws.Codecs.WC.Reply

  @moduletag :acceptance
  @moduletag timeout: 300_000
  @chromium Vws.Test.Browser.chromium()
  if !@chromium do
    @moduletag skip: "chromium is not installed (apt-get install -y chromium)"
  end

  @shots Path.join(Acceptance.root(), "_build/acceptance")

  setup_all do
    :ok = Acceptance.prebuild("dev")
  end

  setup do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.start(
        ~w(mix vws.serve --wc-port #{wc} --http-port #{http} --time-scale 10 --ge2000-baud 2400),
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    [_, url] = Acceptance.await(proc, ~r{Dashboard and MTConnect agent: (http://\S+)}, 120_000)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC/, 30_000)
    %{proc: proc, wc: wc, url: url}
  end

  test "every workstation, partition, sensor number with its trend, link, lease, NC transfer and error, live",
       %{proc: proc, wc: wc, url: url} do
    # 1. an NC program downloaded line by line over a raw WC socket, held half-way while the
    #    page is read: its progress must be on the page
    socket = connect(wc)
    program = ["%", "O1234"] ++ for(i <- 1..80, do: "N#{i} G01 X#{i}.0 Y0 F100") ++ ["M30", "%"]
    {first, rest} = Enum.split(program, 12)
    assert "05A0001" <> _ = request(socket, Acceptance.wc_frame("*0001*M0001DOWNLOAD_HP*"))

    # numbered lines, each answered A nnnn BBB (PROTOCOLS.md §1)
    for {line, n} <- Enum.with_index(first, 1),
        do: assert({:ok, {:line_ack, ^n}} = Reply.decode(request(socket, nc_line(n, line))))

    page = text(page(url))
    assert page =~ ~r/DOWNLOAD_HP 0001 WC .* 12 lines, \d+ bytes \d+ B\/s unknown/
    screenshot(url, "dashboard-download.png")

    # the closing % is answered with the number of lines stored and the program's CRC
    total = length(program)
    crc = Vws.Codecs.WC.ProgramCRC.compute(program)

    for {line, n} <- Enum.with_index(rest, length(first) + 1) do
      expected = if n == total, do: {:line_ack, total, crc}, else: {:line_ack, n}
      assert {:ok, ^expected} = Reply.decode(request(socket, nc_line(n, line)))
    end

    :gen_tcp.close(socket)

    # 2. real commands through the WC link: a lease taken, the gripper closed, the pallet
    #    clamped, and one command that must end in error
    {:ok, client} =
      Client.connect("tcp://127.0.0.1:#{wc}", sequence: 10, numbers: %{"M" => 2, "R" => 1})

    assert :done = Client.await_command(client, "M", 1, 10_000)

    # the program on to the GE-2000 over the DNC link (paced at 2400 Bd: ~8 s), read meanwhile
    # (read once the transfer's rate and time to go are known: after its first blocks)
    {:ok, [{"M", ge}]} = Client.send_commands(client, [{"M", "DOWNLOAD_GE"}])

    page =
      text(Vws.Test.Browser.page(url, until: ~S{/B\/s\s+[\d.]+ s/.test(document.body.innerText)}))

    assert page =~
             ~r/DOWNLOAD_GE #{Vws.Codecs.WC.Command.pad4(ge)} \d{6}\.PRO v\d+ GE-2000 \(DNC\) .*\d+ % \d+ of \d+ blocks, \d+ of \d+ bytes \d+ B\/s [\d.]+ s/

    assert :done = Client.await_command(client, "M", ge, 90_000)
    run(client, "R", "DISABLE_TRAY1")
    run(client, "G", "CLOSE")
    run(client, "H", "CLAMP_PALLET", 60_000)
    {:ok, [{"R", bad}]} = Client.send_commands(client, [{"R", "DO MOVE NOWHERE"}])
    assert {:error, _} = Client.await_command(client, "R", bad, 30_000)

    # 3. the page, once its script has drawn what it polled a few times (the trends)
    dom = Vws.Test.Browser.page(url, updates: 4)
    page = text(dom)

    assert page =~ "Workstation VWS"

    # per partition: state, command, status
    assert page =~ ~r/GRIPPER idle 000\d DONE/
    assert page =~ ~r/HYDRAULIC idle 000\d DONE/
    assert page =~ ~r/ROBOT idle #{pad4(bad)} ERROR /

    # sensor numbers with units, and their trend plots
    assert page =~ ~r/vise jaw width \d+\.\d mm/
    assert page =~ ~r/gripper finger gap \d+\.\d mm/
    assert page =~ ~r/vise clamp force -?\d+ N/
    assert page =~ ~r/pallet clamp force 1 \d{3,} N/
    assert [_ | _] = polylines = Regex.scan(~r/<polyline points="([^"]+)"/, dom)
    assert Enum.any?(polylines, fn [_, points] -> length(String.split(points)) >= 3 end)

    # device statuses as the WC reads them, as words
    assert page =~ "PALLET CLAMPED"
    assert page =~ ~r/SENSORS POLL \d+: GRIPPER FINGER GAP/

    # every link, with state and retries
    for link <- [
          "WC \\(SUN_COMM\\) connected",
          "DAQ #1 \\(HPIB 9\\) (ready|busy) \\d+",
          "HYDRAULIC CONTROLLER \\(HPIB 8\\) (ready|busy) \\d+",
          "GE-2000 \\(DNC\\) \\w+ \\d+",
          "VAL II \\(DDCMP\\) ready \\w+ \\d+",
          "DAQ #2 \\(HPIB 9\\) (ready|busy) \\d+"
        ] do
      assert page =~ ~r/#{link}/, "no link row #{link}"
    end

    # the lease, the NC file done, the error highlighted
    assert page =~ ~r/tray1 robot disabled \d+ (ms|s)/
    assert page =~ "no NC transfer under way"
    assert dom =~ ~r/<div class="error new">[^<]*ROBOT: #{pad4(bad)} ERROR/

    # nothing a person reads is an Elixir term
    for raw <- ["%{", "#PID", "{:", "Elixir.", "%Vws"] do
      refute page =~ raw, "raw term #{raw} on the page"
    end

    screenshot(url, "dashboard.png")
    Client.close(client)
    refute Acceptance.output(proc) =~ "FunctionClauseError"
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

  defdelegate page(url), to: Vws.Test.Browser

  defp screenshot(url, name) do
    File.mkdir_p!(@shots)
    path = Path.join(@shots, name)
    File.rm(path)

    Vws.Test.Browser.screenshot(url, path, {1400, 2400})

    assert File.stat!(path).size > 10_000
    path
  end

  defdelegate text(dom), to: Vws.Test.Browser
end
