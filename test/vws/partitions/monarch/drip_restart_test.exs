defmodule Vws.Partitions.Monarch.DripRestartTest do
  # DRIP_FEED(nnnnnn.PRO[/v][/Nk]) (issue 27 items 2 and 5), end to end: the WC (a raw WC peer)
  # → SUN_COMM → MONARCH → the program library → DNC link → simulated GE-2000, which runs what
  # arrives out of its block buffer.
  use ExUnit.Case, async: true

  alias Vws.CEC.{Interlock, Library, Workstation}
  alias Vws.Codecs.NCModal
  alias Vws.Links.DNC
  alias Vws.Links.DNC.Program
  alias Vws.Sim.GE2000
  alias Vws.Test.WCPeer
  import Vws.Test.Eventually

  @link_opts [reply_timeout: 300, wack_delay: 50, backoff_min: 10, backoff_max: 50]
  @memory 2_048

  # a long program with a tool change, a canned cycle and coolant: line numbers as the library's
  defp program do
    body =
      for i <- 1..400,
          do: "N#{i * 10} G01 X#{rem(i * 37, 1000)}.#{rem(i, 10)} F#{200 + rem(i, 3)}"

    ["%", "O77 (RESTART)", "G21 G17 G90 G54", "T3 M6", "S1500 M3", "M8", "G0 X0 Y0 Z5"] ++
      body ++
      ["G81 X10 Y10 Z-5 R1 F80", "X20", "X30", "G80", "T5 M6", "S900 M4", "G2 X40 Y0 I5 J0 F120"] ++
      body ++ ["M9", "M5", "M30", "%"]
  end

  setup do
    dir = Path.join(System.tmp_dir!(), "vws-drip-restart-#{System.unique_integer([:positive])}")
    on_exit(fn -> File.rm_rf!(dir) end)

    sim =
      start_supervised!(
        {GE2000,
         cycle_time: 60_000, link: @link_opts, memory: @memory, feed_rate: 20_000, tick: 5}
      )

    %{ws: ws, wc: wc} =
      Vws.Test.Workstation.start(
        devices: [ge2000: [endpoint: GE2000.endpoint(sim), status_interval: nil] ++ @link_opts],
        partitions: [monarch: [options: [interlock: [timeout: 300, retry_ms: 50]]]],
        library: dir
      )

    link = Workstation.whereis(ws, :ge2000)
    assert eventually(fn -> DNC.info(link).state == :idle end)
    {:ok, peer} = WCPeer.connect(wc)
    {:ok, _} = Library.store(ws, "77", Program.to_text(program()), source: "iex")
    %{ws: ws, peer: peer, sim: sim}
  end

  defp monarch(peer, number, text), do: WCPeer.monarch(peer, number, text)

  defp assert_ran(sim, text) do
    assert eventually(fn -> GE2000.drip(sim).state == :done end, 30_000)
    drip = GE2000.drip(sim)
    assert drip.received == byte_size(text)
    assert drip.crc == Vws.Codecs.CRC16.compute(text)
    assert drip.max_fill <= @memory
  end

  test "a library program drip-fed whole: no copy through the WC link, the machine runs it exactly",
       %{ws: ws, peer: peer, sim: sim} do
    assert monarch(peer, 1, "DRIP_FEED(000077.PRO)") == "DONE"
    assert_ran(sim, Program.to_text(program()))
    # the machine ran it, it did not store it; MONARCH keeps the table as for any drip feed
    refute "000077.PRO" in GE2000.directory(sim)
    assert Interlock.holds?(ws, :table, :monarch)
  end

  test "restarted at a line: the preamble restores the modal state, logged before the first block",
       %{ws: ws, peer: peer, sim: sim} do
    me = self()
    id = "drip-restart-#{inspect(me)}"

    Vws.Telemetry.attach_many(
      id,
      [[:vws, :monarch, :drip_restart], [:vws, :dnc, :block_sent]],
      # (telemetry is global: only this workstation's)
      fn event, _m, meta, _ -> if meta[:workstation] == ws, do: send(me, {event, meta}) end,
      nil
    )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
    # the dashboard's node history (one per node) shows it too
    :ok = Vws.Ops.Web.History.ensure_started()

    # line 600: in the second body, after the canned cycle ended, tool 5 in the spindle
    n = 600
    assert Enum.at(program(), n - 1) =~ "N1860 G01"
    assert monarch(peer, 2, "DRIP_FEED(000077.PRO/1/N#{n})") == "DONE"

    {:ok, preamble, lines} = NCModal.restart(program(), n)
    assert preamble == ["G21 G17 G90 G54", "T5 M6", "S900 M4", "M8", "G01 F202"]

    assert lines ==
             Enum.take(program(), 2) ++
               ["(RESTART AT LINE 600)" | preamble] ++ Enum.drop(program(), n - 1)

    assert_ran(sim, Program.to_text(lines))

    # the preamble was told (telemetry and log) before the E transmission's first text block
    {:messages, messages} = Process.info(self(), :messages)
    told = Enum.find_index(messages, &match?({[:vws, :monarch, :drip_restart], _}, &1))

    first_text =
      Enum.find_index(messages, &match?({[:vws, :dnc, :block_sent], %{block: b}} when b > 1, &1))

    assert {[:vws, :monarch, :drip_restart],
            %{program: "000077.PRO", version: 1, preamble: ^preamble}} = Enum.at(messages, told)

    assert is_integer(first_text) and told < first_text

    # the dashboard's state: the restart and its preamble, and an event recorded before the DONE
    assert eventually(fn -> Vws.Ops.Web.History.restart(ws) != nil end)

    assert [%{restart: %{program: "000077.PRO", version: 1, line: 600, preamble: ^preamble}}] =
             Vws.Ops.Web.State.build(workstations: [ws]).workstations

    texts = Enum.map(Vws.Ops.Web.History.recent(ws), &"#{&1.where}: #{&1.text}")

    told_at =
      Enum.find_index(
        texts,
        &(&1 =~ "restarts at line 600, restored preamble: G21 G17 G90 G54 / T5 M6")
      )

    assert is_integer(told_at) and told_at < Enum.find_index(texts, &(&1 =~ "MONARCH: 0002 DONE"))

    # the history's record says what the bytes are: version 1 restarted at line 600
    {:ok, %{records: [r]}} = Library.history(ws)

    assert {r.program, r.version, r.note, r.result} ==
             {"000077.PRO", nil, "version 1 restarted at line 600", "DONE"}
  end

  test "bad input ends ERROR in words and sends nothing", %{ws: ws, peer: peer, sim: sim} do
    last = length(program()) - 1

    assert monarch(peer, 3, "DRIP_FEED(000077.PRO/N#{last + 1})") ==
             "ERROR RESTART LINE #{last + 1} BEYOND THE END (LAST BLOCK #{last})"

    # inside the canned cycle: G81 at line 408, G80 at 411
    assert Enum.at(program(), 407) =~ "G81"

    assert monarch(peer, 4, "DRIP_FEED(000077.PRO/N410)") ==
             "ERROR RESTART LINE 410 INSIDE A CANNED CYCLE G81 (NO G80 BEFORE IT)"

    assert monarch(peer, 5, "DRIP_FEED(000078.PRO)") == "ERROR 000078.PRO NOT IN LIBRARY"

    assert monarch(peer, 6, "DRIP_FEED(000077.PRO/9)") ==
             "ERROR 000077.PRO VERSION 9 NOT IN LIBRARY"

    assert monarch(peer, 7, "DRIP_FEED(000077.PRO/N0)") == "ERROR BAD RESTART LINE N0"

    # a program that only ever came from the machine has no released version
    :ok = Vws.Partitions.Monarch.store_from_machine(ws, "000079.PRO", program())
    assert monarch(peer, 8, "DRIP_FEED(000079.PRO)") == "ERROR 000079.PRO HAS NO RELEASED VERSION"

    # a draft version goes to no machine (DOWNLOAD_GE's rule without FORCE)
    {:ok, _} =
      Library.store(ws, "77", Program.to_text(program() ++ ["%"]), source: "cli", state: :draft)

    assert monarch(peer, 10, "DRIP_FEED(000077.PRO/2/N600)") ==
             "ERROR 000077.PRO VERSION 2 NOT RELEASED"

    assert GE2000.state(sim).drips == 0
    assert GE2000.drip(sim) == nil
  end

  test "the table interlock as CYCLE_START: refused while the robot holds the table, nothing sent",
       %{ws: ws, peer: peer, sim: sim} do
    :ok = Interlock.acquire(ws, :table, :robot, 0)
    assert monarch(peer, 9, "DRIP_FEED(000077.PRO/N600)") == "ERROR INTERLOCK TABLE HELD BY ROBOT"
    assert GE2000.state(sim).drips == 0
  end
end
