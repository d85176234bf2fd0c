defmodule Vws.Ops.Web.LibraryStateTest do
  # The dashboard's program library section (issue 18), as /api/state carries it.
  use ExUnit.Case, async: true

  alias Vws.CEC.Library

  @tag :tmp_dir
  test "programs, versions, the machine's directory and where each program stands", %{
    tmp_dir: dir
  } do
    %{ws: ws} = Vws.Test.Workstation.start(library: dir)
    a = "%\nO1\nN1\n%\n"
    {:ok, _} = Library.store(ws, "1", a, source: "wc")
    {:ok, _} = Library.store(ws, "1", "%\nO1\nN2\n%\n", source: "cli")
    {:ok, _} = Library.store(ws, "2", "%\nO2\n%\n", source: "from the machine")

    state = Vws.Ops.Web.State.build()
    [shown] = Enum.filter(state.workstations, &(&1.id == Vws.Ops.Web.State.label(ws)))
    l = shown.library
    assert {l.programs, l.versions, l.read_at} == {2, 3, nil}
    assert l.counts == %{"unknown" => 2}

    :ok =
      Library.record_machine(ws, %{"000001.PRO" => Vws.Links.DNC.Report.entry("000001.PRO", a)})

    l = Vws.Ops.Web.State.library(ws)
    assert l.read_at =~ ~r/^\d{4}-/
    assert l.counts == %{"same" => 1, "absent" => 1}
    rows = Map.new(l.rows, &{&1.name, &1})

    assert %{versions: 2, latest: 2, source: "cli", on_machine: "same as v1 (not the latest)"} =
             rows["000001.PRO"]

    assert %{
             source: "from the machine",
             on_machine: "absent",
             on_machine_class: "absent",
             note: "from the machine, not released"
           } = rows["000002.PRO"]

    assert rows["000001.PRO"].note == ""
    # an edited program sent from the machine: the latest released is still shown, and the newer
    {:ok, _} = Library.store(ws, "1", "%\nO1\nN3\n%\n", source: "from the machine")
    rows = Map.new(Vws.Ops.Web.State.library(ws).rows, &{&1.name, &1})

    assert %{latest: 2, source: "cli", note: "v3 from the machine, not released"} =
             rows["000001.PRO"]

    # a directory entry two different versions share (size and CRC-16): to be read back
    [x, y] = Vws.Test.CRCCollision.programs(3, 2)
    {:ok, _} = Library.store(ws, "3", x)
    {:ok, _} = Library.store(ws, "3", y)
    :ok = Library.record_machine(ws, %{"000003.PRO" => Vws.Links.DNC.Report.entry("x", x)})
    l = Vws.Ops.Web.State.library(ws)
    assert l.counts["ambiguous"] == 1
    row = Enum.find(l.rows, &(&1.name == "000003.PRO"))
    assert row.on_machine =~ "read back to tell" and row.on_machine_class == "ambiguous"

    # the JSON the page reads
    json = IO.iodata_to_binary(Vws.Ops.Web.JSON.encode(state))
    assert json =~ ~s("library":)
    assert Vws.Ops.Web.State.library(:no_such_workstation) == nil
  end

  @tag :tmp_dir
  test "with a cache, a section is read again once older than ten times its reading took", %{
    tmp_dir: dir
  } do
    lib = {:dir, dir}
    cache = :ets.new(:test_cache, [:public])
    {:ok, _} = Library.store(lib, "1", "%\nO1\n%\n")
    assert %{programs: 1} = Vws.Ops.Web.State.library(lib, cache)
    # pretend the last reading took 60 s: the cached section is shown
    [{key, shown, at, _took}] = :ets.lookup(cache, {:library, lib})
    :ets.insert(cache, {key, shown, at, 60_000})
    {:ok, _} = Library.store(lib, "2", "%\nO2\n%\n")
    assert %{programs: 1} = Vws.Ops.Web.State.library(lib, cache)
    # and once that time has passed, it is read again
    :ets.insert(cache, {key, shown, at - 600_001, 60_000})
    assert %{programs: 2} = Vws.Ops.Web.State.library(lib, cache)
  end

  @tag :tmp_dir
  test "the transfer history's newest records, drafts said as drafts, damage counted", %{
    tmp_dir: dir
  } do
    lib = {:dir, dir}
    {:ok, _} = Library.store(lib, "3", "%\nO3\nN1\n%\n", source: "wc")
    {:ok, _} = Library.store(lib, "3", "%\nO3\nN2\n%\n", source: "cli", state: :draft)

    for i <- 1..12 do
      :ok =
        Library.record_transfer(lib,
          program: "000003.PRO",
          version: 1,
          command: "DOWNLOAD_GE(000003.PRO)",
          direction: "to machine",
          bytes: i,
          blocks: 1,
          duration_ms: 20,
          chars_per_s: 50,
          result: if(i == 12, do: "ERROR PROGRAM VERIFY FAILED 000003.PRO", else: "DONE"),
          requester: "WC string 000#{rem(i, 10)} M0001"
        )
    end

    l = Vws.Ops.Web.State.library(lib)
    assert [%{note: "v2 draft, not released"}] = l.rows
    %{damaged: 0, rows: rows} = l.history
    assert length(rows) == 10
    assert Enum.map(rows, & &1.bytes) == Enum.to_list(12..3//-1)

    assert %{
             program: "000003.PRO v1",
             result: "ERROR PROGRAM VERIFY FAILED 000003.PRO",
             severity: "error",
             ms: 20
           } = hd(rows)

    # a damaged record: skipped, counted
    path = Path.join([dir, "history", "transfers.log"])
    bin = File.read!(path)
    <<pre::binary-100, b, post::binary>> = bin
    File.write!(path, <<pre::binary, Bitwise.bxor(b, 1), post::binary>>)

    ExUnit.CaptureLog.capture_log(fn ->
      assert %{damaged: 1, rows: rows} = Vws.Ops.Web.State.library(lib).history
      assert length(rows) == 10
    end)
  end
end
