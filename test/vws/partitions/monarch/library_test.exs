defmodule Vws.Partitions.Monarch.LibraryTest do
  # The program library through MONARCH (issue 18): the WC (a raw WC peer) → SUN_COMM →
  # MONARCH → DNC link → simulated GE-2000, the library a real directory.
  use ExUnit.Case, async: true

  alias Vws.CEC.Library
  alias Vws.Partitions.Monarch
  alias Vws.Sim.GE2000
  alias Vws.Test.{MonarchWC, WCPeer}
  import Vws.Test.Eventually

  @lines ["%", "O4711 (LIBRARY)", "N10 G90 G00 X0 Y0", "N20 G01 X10 F300", "N30 M30", "%"]

  setup do
    MonarchWC.start("vws-monarch-lib")
  end

  defp monarch(peer, number, text) do
    MonarchWC.send_monarch(peer, number, text)
    MonarchWC.finished(peer)
  end

  test "DOWNLOAD_HP stores every program the WC sends as a new version, source wc", %{
    ws: ws,
    peer: peer
  } do
    assert MonarchWC.download_hp(peer, 1, @lines) == "DONE"
    changed = List.replace_at(@lines, 3, "N20 G01 X12 F300")
    assert MonarchWC.download_hp(peer, 2, changed) == "DONE"
    # the same program again is not a new version
    assert MonarchWC.download_hp(peer, 3, changed) == "DONE"

    {:ok, [v1, v2]} = Library.versions(ws, "004711.PRO")
    assert {v1.version, v1.source, v2.version} == {1, "wc", 2}
    assert {:ok, text, _} = Library.read(ws, "004711.PRO", 2)
    assert text == Vws.Links.DNC.Program.to_text(changed)
    # the seed's NC file is there as before
    assert Vws.CEC.Mailbox.nc_file(ws) == changed
  end

  test "DOWNLOAD_GE(name) and DOWNLOAD_GE(name/v) send a library version, verified; the plain " <>
         "DOWNLOAD_GE still sends the NC file",
       %{ws: ws, peer: peer, sim: sim} do
    v1 = "%\nO55\nN10 X1\nN20 M30\n%\n"
    v2 = "%\nO55\nN10 X2\nN20 M30\n%\n"
    {:ok, _} = Library.store(ws, "55", v1, source: "iex")
    {:ok, _} = Library.store(ws, "55", v2, source: "iex")

    assert monarch(peer, 1, "DOWNLOAD_GE(000055.PRO)") == "DONE"
    assert GE2000.program(sim, "000055.PRO") == v2
    assert monarch(peer, 2, "DOWNLOAD_GE(000055.PRO/1)") == "DONE"
    assert GE2000.program(sim, "000055.PRO") == v1
    # the directory read after the download is recorded: the machine holds version 1
    {:ok, c} = Library.compare(ws)
    assert [%{name: "000055.PRO", on_machine: {:same, 1}}] = c.programs

    assert monarch(peer, 3, "DOWNLOAD_GE(000055.PRO/3)") ==
             "ERROR 000055.PRO VERSION 3 NOT IN LIBRARY"

    assert monarch(peer, 4, "DOWNLOAD_GE(000056.PRO)") == "ERROR 000056.PRO NOT IN LIBRARY"

    # a library file that cannot be read: said in words, never as an Elixir term
    {:ok, v} = Library.store(ws, "57", v1)
    {:ok, dir} = Library.dir(ws)
    File.rm!(Path.join(dir, v.file))
    File.mkdir!(Path.join(dir, v.file))

    assert monarch(peer, 8, "DOWNLOAD_GE(000057.PRO)") ==
             "ERROR 000057.PRO NOT READ FROM LIBRARY EISDIR"

    assert monarch(peer, 5, "DOWNLOAD_GE(../../x)") =~ "ERROR BAD PROGRAM FILE"

    # a version over what the machine stores (999,999 bytes, its directory's six digits) is kept
    # by the library for drip feeds; DOWNLOAD_GE of it ends ERROR in words, nothing sent
    big = "%\nO59\n" <> String.duplicate("N1000 G01 X100.5\n", 60_000) <> "M30\n%\n"
    {:ok, _} = Library.store(ws, "59", big)
    downloads = GE2000.state(sim).downloads
    too_large = "ERROR PROGRAM TOO LARGE #{byte_size(big)} BYTES (LIMIT 999999)"
    assert monarch(peer, 9, "DOWNLOAD_GE(000059.PRO)") == too_large
    assert monarch(peer, 10, "DOWNLOAD_GE(000059.PRO/1/FORCE)") == too_large
    refute "000059.PRO" in GE2000.directory(sim)
    assert GE2000.state(sim).downloads == downloads

    assert MonarchWC.download_hp(peer, 6, @lines) == "DONE"
    assert monarch(peer, 7, "DOWNLOAD_GE") == "DONE"
    assert GE2000.program(sim, "004711.PRO") == Vws.Links.DNC.Program.to_text(@lines)
  end

  test "a library program the machine files damaged fails its verify", %{
    ws: ws,
    peer: peer,
    sim: sim
  } do
    {:ok, _} = Library.store(ws, "66", "%\nO66\nN10 X1\n%\n")
    :ok = GE2000.set_fault(sim, {:file_as, &String.replace(&1, "X1", "X7")})
    assert monarch(peer, 1, "DOWNLOAD_GE(000066.PRO)") == "ERROR PROGRAM VERIFY FAILED 000066.PRO"
    {:ok, %{programs: [row]}} = Library.compare(ws)
    assert row.on_machine == :differs
  end

  test "compare: same / differs / absent, by directory CRC and by full read-back", %{
    ws: ws,
    peer: peer,
    sim: sim
  } do
    same = "%\nO1\nN10 X1.000000\n%\n"
    {:ok, _} = Library.store(ws, "1", same)
    {:ok, _} = Library.store(ws, "2", "%\nO2\nN10 X2\n%\n")
    {:ok, _} = Library.store(ws, "3", "%\nO3\nN10 X3\n%\n")
    GE2000.put_program(sim, "000001.PRO", same)
    GE2000.put_program(sim, "000002.PRO", "%\nO2\nN10 X9\n%\n")
    GE2000.put_program(sim, "000009.PRO", "%\nO9\n%\n")

    {:ok, c} = Monarch.compare(ws, read_back: true)

    assert Map.new(c.programs, &{&1.name, &1.on_machine}) ==
             %{"000001.PRO" => {:same, 1}, "000002.PRO" => :differs, "000003.PRO" => :absent}

    assert Enum.find(c.programs, &(&1.name == "000001.PRO")).read_back == :same
    assert c.machine_only == ["000009.PRO"]
    text = Enum.join(Vws.Ops.LibraryText.format_compare(c), "\n")
    assert text =~ ~r/000001.PRO .*on the machine: same, read back: same/
    assert text =~ ~r/000002.PRO .*on the machine: differs/
    assert text =~ ~r/000003.PRO .*on the machine: absent/

    # from the WC: COMPARE_GE(name) reads the program back whole
    assert monarch(peer, 1, "COMPARE_GE(000001.PRO)") == "DONE"
    # read back, and what differs said in lines (issue 27)
    assert monarch(peer, 2, "COMPARE_GE(000002.PRO)") ==
             "ERROR PROGRAM DIFFERS 000002.PRO FROM V1 LINES -1 +1 AT LINE 3"

    assert monarch(peer, 3, "COMPARE_GE(000003.PRO)") == "ERROR PROGRAM ABSENT 000003.PRO"
    assert monarch(peer, 4, "COMPARE_GE(000008.PRO)") == "ERROR 000008.PRO NOT IN LIBRARY"
    assert monarch(peer, 5, "COMPARE_GE") == "DONE"

    # a difference the directory's size and CRC-16 cannot see (another text with the same
    # CRC) is found only by the read-back
    forged = same_crc_as(same)
    assert forged != same and byte_size(forged) == byte_size(same)
    GE2000.put_program(sim, "000001.PRO", forged)
    {:ok, c} = Monarch.compare(ws)
    assert hd(c.programs).on_machine == {:same, 1}
    {:ok, c} = Monarch.compare(ws, read_back: ["000001.PRO"])
    assert %{on_machine: :differs, read_back: :differs} = hd(c.programs)

    assert monarch(peer, 6, "COMPARE_GE(000001.PRO)") ==
             "ERROR PROGRAM DIFFERS 000001.PRO FROM V1 LINES -1 +1 AT LINE 3"
  end

  # "%\nO1\nN10 Xd.dddddd\n%\n" text of the same length and CRC-16/ARC as `text`
  defp same_crc_as(text) do
    crc = Vws.Codecs.CRC16.compute(text)

    Stream.iterate(0, &(&1 + 1))
    |> Stream.map(fn i ->
      digits = String.pad_leading(Integer.to_string(i), 7, "0")
      "%\nO1\nN10 X" <> String.slice(digits, 0, 1) <> "." <> String.slice(digits, 1, 6) <> "\n%\n"
    end)
    |> Enum.find(&(Vws.Codecs.CRC16.compute(&1) == crc and &1 != text))
  end

  defp upload_sun(peer, number) do
    s = MonarchWC.seq()
    WCPeer.send_string(peer, s, [{"M", number, "UPLOAD_SUN"}])
    assert Vws.Codecs.WC.Reply.decode(WCPeer.recv_line(peer)) == {:ok, {:ack, s}}
    lines = WCPeer.upload_lines(peer)
    {lines, MonarchWC.finished(peer)}
  end

  test "a program the operator sends from the machine is a library version from the machine, " <>
         "not released, and never NC_UP",
       %{ws: ws, sim: sim, peer: peer} do
    test_pid = self()
    handler = "lib-received-#{System.unique_integer([:positive])}"

    :ok =
      Vws.Telemetry.attach(
        handler,
        [:vws, :monarch, :program_received],
        fn _, _, md, _ -> if md.workstation == ws, do: send(test_pid, {:received, md.result}) end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(handler) end)
    text = "%\nO100 (FROM THE PANEL)\nN10 G01 X1\nN20 M30\n%\n"
    :ok = GE2000.put_program(sim, "000100.PRO", text)

    assert GE2000.send_program(sim, "000100.PRO") == :ok
    assert_receive {:received, :ok}, 10_000
    {:ok, [v1]} = Library.versions(ws, "000100.PRO")
    assert {v1.source, v1.origin, v1.released} == {"from the machine", :machine, false}
    assert {:ok, ^text, _} = Library.read(ws, "000100.PRO", 1)
    assert Library.read(ws, "000100.PRO") == {:error, :not_released}

    # sent again unchanged: the library has these bytes already, nothing new
    assert GE2000.send_program(sim, "000100.PRO") == :ok
    assert_receive {:received, :ok}, 10_000
    assert {:ok, [_]} = Library.versions(ws, "000100.PRO")

    # NC_UP is the WC's (UPLOAD_GE): untouched
    assert Vws.CEC.Mailbox.nc_up(ws) == []
    # not released: DOWNLOAD_GE(name) does not send it, only one that names the version
    GE2000.put_program(sim, "000100.PRO", "%\nO100\n%\n")

    assert monarch(peer, 1, "DOWNLOAD_GE(000100.PRO)") ==
             "ERROR 000100.PRO HAS NO RELEASED VERSION"

    assert GE2000.program(sim, "000100.PRO") == "%\nO100\n%\n"
    # a draft goes to a machine only when the command says FORCE (issue 27)
    assert monarch(peer, 2, "DOWNLOAD_GE(000100.PRO/1)") ==
             "ERROR 000100.PRO VERSION 1 NOT RELEASED"

    assert GE2000.program(sim, "000100.PRO") == "%\nO100\n%\n"
    assert monarch(peer, 3, "DOWNLOAD_GE(000100.PRO/1/FORCE)") == "DONE"
    assert GE2000.program(sim, "000100.PRO") == text
  end

  test "what the WC asked for is what it gets: UPLOAD_GE, then a program sent from the machine, " <>
         "then UPLOAD_SUN brings UPLOAD_GE's program",
       %{ws: ws, sim: sim, peer: peer} do
    asked = "%\nO4321 (ASKED FOR)\nN10 G01 X1\nN20 M30\n%\n"
    unasked = "%\nO5555 (SENT AT THE PANEL)\nN10 G01 X9\nN20 M30\n%\n"
    :ok = GE2000.put_program(sim, "004321.PRO", asked)
    :ok = GE2000.put_program(sim, "005555.PRO", unasked)

    assert monarch(peer, 1, "UPLOAD_GE(004321.PRO)") == "DONE"
    assert GE2000.send_program(sim, "005555.PRO") == :ok
    assert eventually(fn -> match?({:ok, [_]}, Library.versions(ws, "005555.PRO")) end)

    assert upload_sun(peer, 2) == {Vws.Links.DNC.Program.from_text(asked), "DONE"}
    assert {:ok, ^unasked, %{released: false}} = Library.read(ws, "005555.PRO", 1)
  end

  test "an edited program sent from the machine does not become what DOWNLOAD_GE(name) sends, " <>
         "until it is released",
       %{ws: ws, sim: sim, peer: peer} do
    released = "%\nO4321\nN10 G01 X1\nN20 M30\n%\n"
    edited = "%\nO4321\nN10 G01 X1.5 (OPERATOR)\nN20 M30\n%\n"
    {:ok, _} = Library.store(ws, "4321", released, source: "wc")
    :ok = GE2000.put_program(sim, "004321.PRO", edited)
    assert GE2000.send_program(sim, "004321.PRO") == :ok
    assert eventually(fn -> match?({:ok, [_, _]}, Library.versions(ws, "004321.PRO")) end)

    assert monarch(peer, 1, "DOWNLOAD_GE(004321.PRO)") == "DONE"
    assert GE2000.program(sim, "004321.PRO") == released
    assert monarch(peer, 2, "DOWNLOAD_GE(004321.PRO/2/FORCE)") == "DONE"
    assert GE2000.program(sim, "004321.PRO") == edited
    # the directory shows the machine holds v2, which came from the machine
    {:ok, c} = Library.compare(ws)
    text = Enum.join(Vws.Ops.LibraryText.format_compare(c), "\n")
    assert text =~ "same as v2 (from the machine, not released)"

    {:ok, v3} = Library.release(ws, "4321", 2, source: "iex")
    assert {v3.version, v3.released} == {3, true}
    assert monarch(peer, 3, "DOWNLOAD_GE(000100.PRO)") == "ERROR 000100.PRO NOT IN LIBRARY"
    GE2000.put_program(sim, "004321.PRO", released)
    assert monarch(peer, 4, "DOWNLOAD_GE(004321.PRO)") == "DONE"
    assert GE2000.program(sim, "004321.PRO") == edited
    {:ok, c} = Library.compare(ws)
    assert [%{on_machine: {:same, 3}}] = c.programs
  end

  test "size and CRC-16 shared by two versions: the read-back's digest names the version the " <>
         "machine holds",
       %{ws: ws, sim: sim, peer: peer} do
    [a, b, c] = Vws.Test.CRCCollision.programs(77, 3)
    {:ok, _} = Library.store(ws, "77", a, source: "wc")
    {:ok, _} = Library.store(ws, "77", b, source: "wc")

    for {on_machine, named} <- [{a, 1}, {b, 2}] do
      GE2000.put_program(sim, "000077.PRO", on_machine)
      # the directory alone cannot tell
      assert monarch(peer, 1, "COMPARE_GE") == "DONE"
      {:ok, %{programs: [row]}} = Library.compare(ws)
      assert row.on_machine == {:ambiguous, [1, 2]}
      # the read-back can (Monarch.compare reads back what the directory cannot tell)
      {:ok, %{programs: [row]}} = Monarch.compare(ws)
      assert {row.on_machine, row.read_back} == {{:same, named}, :same}
      assert monarch(peer, 2, "COMPARE_GE(000077.PRO)") == "DONE"
    end

    # a third text of that size and CRC: no version of the library
    GE2000.put_program(sim, "000077.PRO", c)
    {:ok, %{programs: [row]}} = Monarch.compare(ws)
    assert {row.on_machine, row.read_back} == {:differs, :differs}

    assert monarch(peer, 3, "COMPARE_GE(000077.PRO)") =~
             ~r/^ERROR PROGRAM DIFFERS 000077.PRO FROM V2 LINES -\d+ \+\d+ AT LINE \d+$/
  end
end
