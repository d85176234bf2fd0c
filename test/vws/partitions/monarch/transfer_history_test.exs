defmodule Vws.Partitions.Monarch.TransferHistoryTest do
  # The transfer history (issue 27) end to end: the WC (a raw WC peer) → SUN_COMM → MONARCH →
  # DNC link → simulated GE-2000 over its wire protocol, the library a real directory.
  use ExUnit.Case, async: true

  alias Vws.CEC.Library
  alias Vws.Partitions.Monarch
  alias Vws.Sim.GE2000
  alias Vws.Test.MonarchWC
  import Vws.Test.Eventually

  @nc ["%", "O100 (NC FILE)", "N10 G90 G00 X0 Y0", "N20 G01 X10 F300", "N30 M30", "%"]
  @v1 "%\nO100 (V1)\nN10 G90 G00 X0 Y0\nN20 G01 X10 F300\nN30 M30\n%\n"
  @v2 "%\nO100 (V2 DRAFT)\nN10 G90 G00 X0 Y0\nN20 G01 X12 F300\nN30 M30\n%\n"

  # Every form of every Monarch command. A kind of Vws.Codecs.Commands.kinds/0 missing here
  # fails the first test, so a new command is enumerated here and its transfers checked.
  # DOWNLOAD_HP and UPLOAD_SUN are transfers on the WC link, carried out by SUN_COMM, not DNC.
  @forms [
    cycle_start: ["CYCLE_START"],
    release_table: ["RELEASE_TABLE"],
    status: ["STATUS"],
    download_hp: [],
    upload_sun: [],
    download_ge: [
      "DOWNLOAD_GE",
      "DOWNLOAD_GE(000100.PRO)",
      "DOWNLOAD_GE(000100.PRO/1)",
      "DOWNLOAD_GE(000100.PRO/2)",
      "DOWNLOAD_GE(000100.PRO/2/FORCE)"
    ],
    drip_feed: [
      "DRIP_FEED",
      "DRIP_FEED(000100.PRO)",
      "DRIP_FEED(000100.PRO/1/N3)",
      "DRIP_FEED(000100.PRO/2)"
    ],
    compare_ge: ["COMPARE_GE", "COMPARE_GE(000100.PRO)"],
    upload_ge: ["UPLOAD_GE(000100.PRO)"],
    program_select: ["PROGRAM_SELECT(000100)"],
    program_delete: ["PROGRAM_DELETE(000100.PRO)"],
    table: ["TABLE(1/3)"]
  ]

  setup do
    MonarchWC.start("vws-history-e2e")
  end

  defp monarch(peer, number, text) do
    s = MonarchWC.send_monarch(peer, number, text)
    {s, MonarchWC.finished(peer)}
  end

  defp records(ws) do
    {:ok, %{records: newest_first, damaged: []}} = Library.history(ws)
    Enum.reverse(newest_first)
  end

  # the program transfers the link made (its progress telemetry at each one's end), as
  # {program, direction} — seen independently of MONARCH's recording
  defp watch_transfers(ws) do
    test_pid = self()
    id = "history-watch-#{System.unique_integer([:positive])}"

    :ok =
      Vws.Telemetry.attach(
        id,
        [:vws, :dnc, :progress],
        fn _, m, md, _ ->
          # (an R command's own block goes out too, with no program text: not a transfer)
          if md.workstation == ws and md.ended != false and
               not (md.direction == :out and m.program_bytes == 0),
             do: send(test_pid, {:transfer, md.program, md.direction})
        end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
  end

  defp transfers_seen(acc \\ []) do
    receive do
      {:transfer, program, direction} -> transfers_seen([{program, direction} | acc])
    after
      0 -> Enum.reverse(acc)
    end
  end

  test "every Monarch command that moves a program over the DNC link is in the history: one " <>
         "record per transfer the link made, with its result",
       %{ws: ws, peer: peer, sim: sim} do
    kinds = Vws.Codecs.Commands.kinds()[:monarch] |> Keyword.keys() |> Enum.sort()
    assert Keyword.keys(@forms) |> Enum.sort() == kinds

    for {kind, texts} <- @forms, text <- texts do
      {:ok, command} = Vws.Codecs.Commands.parse(:monarch, text)
      assert kind == if(is_tuple(command), do: elem(command, 0), else: command)
    end

    {:ok, _} = Library.store(ws, "100", @v1, source: "wc")
    {:ok, _} = Library.store(ws, "100", @v2, source: "cli", state: :draft)
    assert MonarchWC.download_hp(peer, 1, @nc) == "DONE"
    watch_transfers(ws)

    moved =
      for {{_kind, texts}, i} <- Enum.with_index(@forms), text <- texts do
        :ok = GE2000.put_program(sim, "000100.PRO", @v1)
        before = length(records(ws))
        _ = transfers_seen()
        {s, status} = monarch(peer, rem(i * 10 + String.length(text), 9000) + 2, text)
        seen = transfers_seen()
        new = Enum.drop(records(ws), before)

        # one record per request; a request the line broke off and MONARCH made again is
        # one record, the link's transfers beyond it counted in its retries
        assert length(new) <= length(seen) and (seen == [] or new != []),
               "#{text}: #{length(seen)} program transfers on the link, " <>
                 "#{length(new)} recorded: #{inspect(new)}"

        assert Enum.sum(Enum.map(new, & &1.retries)) >= length(seen) - length(new)

        for r <- new do
          # (the seed's DOWNLOAD_GE names no file on the link: the machine files it by its O word)
          assert {r.program, r.direction} in Enum.map(seen, fn {p, d} ->
                   {p || "000100.PRO", if(d == :out, do: "to machine", else: "from machine")}
                 end),
                 text

          assert r.command == text
          assert r.result == status, text
          assert r.requester =~ ~r/^WC string #{Vws.Codecs.WC.Command.pad4(s)} M\d{4}$/
          assert r.bytes > 0 and r.blocks > 0
        end

        {text, length(new)}
      end

    # the paths that move programs were all taken
    for text <- ~w[DOWNLOAD_GE DOWNLOAD_GE(000100.PRO) DRIP_FEED UPLOAD_GE(000100.PRO)
                   COMPARE_GE(000100.PRO) DOWNLOAD_GE(000100.PRO/2/FORCE)] do
      assert {text, 1} in moved, "#{text}: #{inspect(moved)}"
    end

    # from the library, and restarted at a line (issue 27)
    assert {"DRIP_FEED(000100.PRO)", 1} in moved, inspect(moved)
    assert {"DRIP_FEED(000100.PRO/1/N3)", 1} in moved, inspect(moved)

    # the draft without FORCE: nothing sent, nothing recorded
    assert {"DOWNLOAD_GE(000100.PRO/2)", 0} in moved
    assert {"DRIP_FEED(000100.PRO/2)", 0} in moved

    # a program sent from the machine's panel
    before = length(records(ws))
    assert GE2000.send_program(sim, "000100.PRO") == :ok
    assert eventually(fn -> length(records(ws)) == before + 1 end)
    [r] = Enum.drop(records(ws), before)

    assert {r.requester, r.direction, r.result, r.version} ==
             {"machine panel", "from machine", "DONE", 1}

    assert transfers_seen() == [{"000100.PRO", :in}]
  end

  test "what a record says: version, bytes, blocks, rate, retries, result words; a verify " <>
         "failure and a broken line recorded as the WC saw them",
       %{ws: ws, peer: peer, sim: sim} do
    {:ok, v1} = Library.store(ws, "100", @v1, source: "wc")
    {_s, "DONE"} = monarch(peer, 1, "DOWNLOAD_GE(000100.PRO)")
    [r] = records(ws)
    assert r.program == "000100.PRO" and r.version == 1
    assert r.digest == String.slice(v1.digest, 0, 16)
    assert r.bytes == byte_size(@v1)
    assert r.blocks == 1

    assert {r.operation, r.direction, r.result, r.retries} ==
             {"part program", "to machine", "DONE", 0}

    assert r.duration_ms >= 0 and r.chars_per_s >= 0

    # the machine files it damaged: the line's transfer went, the command ends ERROR
    :ok = GE2000.set_fault(sim, {:file_as, &String.replace(&1, "X10", "X17")})
    {_s, status} = monarch(peer, 2, "DOWNLOAD_GE(000100.PRO)")
    assert status == "ERROR PROGRAM VERIFY FAILED 000100.PRO"
    assert List.last(records(ws)).result == status

    # COMPARE_GE of the damaged file: the read-back and what differs
    :ok = GE2000.set_fault(sim, :none)
    {_s, status} = monarch(peer, 3, "COMPARE_GE(000100.PRO)")
    assert status == "ERROR PROGRAM DIFFERS 000100.PRO FROM V1 LINES -1 +1 AT LINE 4"
    last = List.last(records(ws))
    assert {last.direction, last.version, last.result} == {"from machine", nil, status}
    assert last.note == "differs from v1: 1 lines removed, 1 added, first at line 4"
    {:ok, d} = Library.diff_machine(ws, "000100.PRO")

    assert Vws.Ops.LibraryText.format_diff(d.diff) |> Enum.filter(&(&1 =~ ~r/^[-+] /)) ==
             ["- N20 G01 X10 F300", "+ N20 G01 X17 F300"]

    # a silent machine: the link's words, its retries counted
    :ok = GE2000.set_fault(sim, :silent)
    {_s, status} = monarch(peer, 4, "UPLOAD_GE(000100.PRO)")
    assert status =~ ~r/^ERROR DNC/
    last = List.last(records(ws))
    assert last.result == status and last.bytes == 0
    assert last.retries > 0

    # from iex: recorded at once, "iex"
    :ok = GE2000.set_fault(sim, :none)
    :ok = GE2000.put_program(sim, "000100.PRO", @v1)
    {:ok, _} = Monarch.compare(ws, read_back: true)
    last = List.last(records(ws))
    assert {last.requester, last.result, last.version} == {"iex", "DONE", 1}
  end

  test "a diff of a program the machine does not hold ends ERROR in words, nothing read", %{
    ws: ws,
    peer: peer
  } do
    {:ok, _} = Library.store(ws, "100", @v1, source: "wc")
    watch_transfers(ws)
    {_s, status} = monarch(peer, 1, "COMPARE_GE(000100.PRO)")
    assert status == "ERROR PROGRAM ABSENT 000100.PRO"
    assert transfers_seen() == []
    assert records(ws) == []
    assert Library.diff_machine(ws, "000100.PRO") == {:error, :not_read_back}
  end
end
