defmodule Vws.CEC.LibraryTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.CEC.Library

  doctest Library
  doctest Vws.Test.CRCCollision

  @prog "%\nO1234 (BRACKET)\nN10 G90 G00 X0 Y0\nN20 M30\n%\n"

  setup do
    dir = Path.join(System.tmp_dir!(), "vws-lib-#{System.unique_integer([:positive])}")
    on_exit(fn -> File.rm_rf!(dir) end)
    %{lib: {:dir, dir}, dir: dir}
  end

  test "every store is a new version with who stored it, when, size and CRC", %{lib: lib} do
    before = DateTime.utc_now() |> DateTime.truncate(:millisecond)
    {:ok, v1} = Library.store(lib, "1234", @prog, source: "wc")
    {:ok, v2} = Library.store(lib, "001234.PRO", @prog <> "", source: "from the machine")
    {:ok, v3} = Library.store(lib, "O1234", String.replace(@prog, "X0", "X5"), source: "cli")

    assert {v1.version, v2.version, v3.version} == {1, 2, 3}
    assert v1.size == byte_size(@prog) and v1.crc == Vws.Codecs.CRC16.compute(@prog)
    assert DateTime.compare(v1.at, before) != :lt

    {:ok, [p]} = Library.list(lib)
    assert p.name == "001234.PRO"

    assert Enum.map(p.versions, &{&1.version, &1.source}) ==
             [{1, "wc"}, {2, "from the machine"}, {3, "cli"}]

    assert p.versions |> hd() |> Map.take([:size, :crc, :at]) == Map.take(v1, [:size, :crc, :at])
    assert {:ok, @prog, %{version: 2}} = Library.read(lib, "1234", 2)
    assert {v1.released, v2.released, v3.released} == {true, false, true}
    assert {v1.origin, v2.origin} == {:library, :machine}
    assert v1.digest == Library.digest(@prog) and v2.digest == v1.digest
    assert {:ok, text, %{version: 3}} = Library.read(lib, "1234")
    assert text =~ "X5"
    assert {:error, :not_found} = Library.read(lib, "1234", 4)
    assert {:error, :not_found} = Library.versions(lib, "999")
  end

  test "bad names, sources and sizes store nothing and never leave the directory",
       %{dir: parent} do
    # the library one level down in a directory of this test's own: a name that left it would
    # show beside it (not in the shared temporary directory, where anything may be)
    dir = Path.join(parent, "lib")
    lib = {:dir, dir}

    for bad <- [
          "../x",
          "/etc/passwd",
          "001234.PRO/../../x",
          "1234567",
          "",
          "ABC",
          "12~3",
          nil,
          "a\0b"
        ] do
      assert Library.store(lib, bad, @prog) == {:error, :bad_name}, inspect(bad)
    end

    assert Library.store(lib, "1", @prog, source: "Bad/Source") == {:error, :bad_source}
    assert Library.store(lib, "1", @prog, source: "a~b") == {:error, :bad_source}
    assert Library.store(lib, "1", @prog, source: "shop\n") == {:error, :bad_source}
    # the library keeps up to 64 MiB (a drip feed's program); what the GE-2000 stores is bounded
    # apart (999,999 bytes, its directory's six digits: Vws.Links.DNC.Program.check_size/1)
    assert Library.max_bytes() == 64 * 1024 * 1024
    assert Library.max_bytes() > Vws.Links.DNC.Program.max_stored_bytes()
    big = :binary.copy("N", Library.max_bytes() + 1)
    assert Library.store(lib, "1", big) == {:error, :too_large}
    assert Library.list(lib) == {:ok, []}
    refute File.exists?(Path.join(Path.dirname(dir), "x"))
    assert Library.store(:no_such_workstation, "1", @prog) == {:error, :no_library}
  end

  test "a program over the 999,999 bytes the machine stores is kept, its size in the file name " <>
         "with as many digits as it takes; a library named in the old six-digit form reads as before",
       %{lib: lib, dir: dir} do
    # written by hand as every library was before programs over 999,999 bytes: six-digit size
    old_text = "%\nO18\nN1 X1\nM30\n%\n"
    crc = String.pad_leading(Integer.to_string(Vws.Codecs.CRC16.compute(old_text), 16), 4, "0")
    digest = Library.digest(old_text)
    old = "000018.PRO~000001~20261125T090000.123Z~wc~000018~#{crc}~#{digest}"
    File.mkdir_p!(Path.join(dir, ".v"))
    File.write!(Path.join(dir, old), old_text)
    File.ln_s!(Path.join("..", old), Path.join([dir, ".v", "000018.PRO~000001"]))

    # 1,500,024 bytes: over what the machine stores (Vws.Test.MonarchWC.long_program/1)
    big = Vws.Test.MonarchWC.long_program(18)
    assert byte_size(big) == 1_500_024
    assert Vws.Links.DNC.Program.check_size(big) != :ok
    assert Library.check_program(big) == :ok
    {:ok, v2} = Library.store(lib, "18", big, source: "cli")
    assert {v2.version, v2.size} == {2, 1_500_024}
    assert v2.file =~ ~r/^000018\.PRO~000002~[^~]+~cli~1500024~[0-9A-F]{4}~[0-9a-f]{64}$/

    assert {:ok, [p]} = Library.list(lib)
    assert [%{file: ^old, size: 18, digest: ^digest}, %{size: 1_500_024}] = p.versions
    assert {:ok, ^old_text, %{version: 1}} = Library.read(lib, "18", 1)
    assert {:ok, ^big, %{version: 2}} = Library.read(lib, "18")
    # the same bytes again are the same version, whatever their size
    assert {:ok, %{version: 2}} = Library.store(lib, "18", big, only_if_changed: true)
    # a damaged big version is caught as any other
    File.write!(Path.join(dir, v2.file), binary_part(big, 0, byte_size(big) - 1) <> "X")
    assert Library.read(lib, "18", 2) == {:error, :damaged}
  end

  test "version file names: sizes from 0 to the library's bound read back as written" do
    at = ~U[2026-11-27 04:00:00.123Z]

    for size <- [0, 1, 999_999, 1_000_000, 1_500_024, Library.max_bytes()] do
      v = %{name: "000001.PRO", version: 3, at: at, source: "wc", size: size, crc: 0xBB3D}
      v = Map.put(v, :digest, String.duplicate("a", 64))
      file = Vws.CEC.Library.Files.file_name(v)

      assert [%{size: ^size, version: 3, crc: 0xBB3D, file: ^file}] =
               Vws.CEC.Library.Files.parse_files([file])
    end
  end

  test "stores racing for one program get distinct numbers, none lost", %{lib: lib} do
    results =
      1..24
      |> Enum.map(fn i -> Task.async(fn -> Library.store(lib, "77", "%\nO77\nN#{i}\n%\n") end) end)
      |> Enum.map(&Task.await/1)

    numbers = for {:ok, v} <- results, do: v.version
    assert Enum.sort(numbers) == Enum.to_list(1..24)
    {:ok, vs} = Library.versions(lib, "77")
    assert length(vs) == 24

    for v <- vs do
      {:ok, text, _} = Library.read(lib, "77", v.version)
      assert text =~ "O77"
    end
  end

  test "a store that crashed leaves no version visible, and the library goes on",
       %{lib: lib, dir: dir} do
    {:ok, _} = Library.store(lib, "5", "%\nO5\n%\n")
    # a crash after the temporary file was written: not a version
    File.write!(Path.join(dir, ".tmp-000005.PRO-1"), "%\nO5\nHALF")
    # a crash after the number was taken, before the rename: version 2 never appears
    File.ln_s!(
      "../000005.PRO~000002~20261125T090000.000Z~wc~000009~0000",
      Path.join([dir, ".v", "000005.PRO~000002"])
    )

    {:ok, [p]} = Library.list(lib)
    assert Enum.map(p.versions, & &1.version) == [1]
    assert Library.version(lib, "5", 2) == {:error, :not_found}

    {:ok, v} = Library.store(lib, "5", "%\nO5\nN2\n%\n")
    assert v.version == 3
    assert {:ok, "%\nO5\nN2\n%\n", _} = Library.read(lib, "5")

    # tidy removes old temporary files only
    assert :ok = Library.tidy(lib, 0)
    refute File.exists?(Path.join(dir, ".tmp-000005.PRO-1"))
  end

  test "a version damaged on disk reads as damaged, never as the program", %{lib: lib, dir: dir} do
    {:ok, v} = Library.store(lib, "9", "%\nO9\nN10 X1\n%\n")
    File.write!(Path.join(dir, v.file), "%\nO9\nN10 X7\n%\n")
    assert Library.read(lib, "9") == {:error, :damaged}
  end

  test "killed in the middle of storing: every visible version is whole", %{lib: lib} do
    big = :binary.copy("N10 G01 X1.0 Y2.0 F300\n", 200_000)

    for _ <- 1..5 do
      pid =
        spawn(fn -> for _ <- 1..100, do: Library.store(lib, "42", "%\nO42\n" <> big <> "%\n") end)

      Process.sleep(:rand.uniform(60))
      Process.exit(pid, :kill)
    end

    case Library.versions(lib, "42") do
      {:ok, vs} -> for v <- vs, do: assert({:ok, _, _} = Library.read(lib, "42", v.version))
      {:error, :not_found} -> :ok
    end
  end

  test "import a file, export a version, diff two versions", %{lib: lib, dir: dir} do
    src = dir <> "-in.nc"
    out = dir <> "-out.nc"
    on_exit(fn -> File.rm(src) && File.rm(out) end)
    File.write!(src, @prog)

    assert {:ok, %{name: "001234.PRO", version: 1, source: "cli"}} = Library.import_file(lib, src)
    File.write!(src, String.replace(@prog, "N20 M30", "N15 M05\nN20 M30"))
    assert {:ok, %{version: 2}} = Library.import_file(lib, src, name: "1234")

    assert {:ok, %{version: 1}} = Library.export(lib, "1234", 1, out)
    assert File.read!(out) == @prog

    {:ok, diff} = Library.diff(lib, "1234", 1, 2)

    assert Vws.Ops.LibraryText.format_diff(diff)
           |> Enum.filter(&String.starts_with?(&1, ["+", "-"])) == [
             "+ N15 M05"
           ]

    {:ok, same} = Library.diff(lib, "1234", 2, :latest)
    assert Vws.Ops.LibraryText.format_diff(same) == []

    File.write!(src, "N10 G00\n")
    assert Library.import_file(lib, src) == {:error, {:not_a_program, :no_start}}
  end

  test "import refuses what is not an NC program, with the reason, and stores nothing",
       %{lib: lib, dir: dir} do
    src = dir <> "-bad.nc"
    on_exit(fn -> File.rm(src) end)

    refused = fn bytes ->
      File.write!(src, bytes)
      assert {:error, {:not_a_program, why}} = Library.import_file(lib, src, name: "1234")
      assert Vws.Ops.LibraryText.program_refusal(why) =~ ~r/^not an NC program: [a-z0-9]/
      why
    end

    python = "#!/usr/bin/env python3\nimport os\nx = {'a':1}\nprint(os.getcwd())\n"
    assert refused.(python) == :no_start
    assert refused.("%\nO1234\nN10 G00\n") == :no_end
    assert refused.("%\nO1234\nN10 G00\n%") == :no_end
    assert refused.("%\n%\n") == :no_program_number
    assert refused.("%\nN10 G00 (O1234)\nO1234\n%\n") == :no_program_number
    assert refused.("%\nO1234567\nN10\n%\n") == :bad_program_number
    assert refused.("%\nO1234\nN10 G00" <> <<2>> <> "X1\n%\n") == {:control, 2, 3}
    assert refused.("%\nO1234\nN10\e[31m\n%\n") == {:control, 0x1B, 3}
    assert refused.("%\nO1234\n" <> <<0, 1, 2, 255>> <> "\n%\n") == {:binary, 8}
    assert refused.("%\nO1234\n" <> <<0xFF, 0xFE>> <> "\n%\n") == {:binary, 8}

    # more than the library keeps: refused by its size, before a byte is read (a sparse file)
    {:ok, fd} = :file.open(String.to_charlist(src), [:write, :binary])
    {:ok, _} = :file.position(fd, Library.max_bytes() + 1)
    :ok = :file.truncate(fd)
    :ok = :file.close(fd)
    assert {:error, {:not_a_program, {:too_large, size}}} = Library.import_file(lib, src)
    assert size == Library.max_bytes() + 1
    assert Vws.Ops.LibraryText.program_refusal({:too_large, size}) =~ "the library keeps"
    assert Library.list(lib) == {:ok, []}

    # what the shop writes is still taken: EIA, comments before the O word, CR LF, tabs
    for {text, name} <- [
          {"%\n:77\nN10 G00\n%\n", "000077.PRO"},
          {"%\n(BRACKET)\n\nO0042 (ROUGH)\nN10\tG00\n%\n", "000042.PRO"},
          {"%\r\nO43\r\nN10 G00\r\n%\r\n", "000043.PRO"},
          {"%\nO44\n" <> String.duplicate("N10 G01 X1.0 Y2.0 F300\n", 43_000) <> "%\n",
           "000044.PRO"}
        ] do
      File.write!(src, text)
      assert {:ok, %{name: ^name, version: 1}} = Library.import_file(lib, src)
    end
  end

  test "import: a copy of the latest version is not stored again", %{lib: lib, dir: dir} do
    src = dir <> "-dup.nc"
    on_exit(fn -> File.rm(src) end)
    File.write!(src, @prog)
    assert {:ok, %{version: 1}} = Library.import_file(lib, src)
    assert {:same, %{version: 1}} = Library.import_file(lib, src)

    File.write!(src, String.replace(@prog, "X0", "X5"))
    assert {:ok, %{version: 2}} = Library.import_file(lib, src)
    assert {:same, %{version: 2}} = Library.import_file(lib, src, name: "1234")

    # version 1 again is a new version: it is not the latest
    File.write!(src, @prog)
    assert {:ok, %{version: 3}} = Library.import_file(lib, src)
    assert {:ok, versions} = Library.versions(lib, "1234")
    assert length(versions) == 3
  end

  test "compare: same (which version), differs, absent, unknown, and files only on the machine",
       %{lib: lib} do
    a1 = "%\nO1\nN1\n%\n"
    a2 = "%\nO1\nN2\n%\n"
    {:ok, _} = Library.store(lib, "1", a1)
    {:ok, _} = Library.store(lib, "1", a2)
    {:ok, _} = Library.store(lib, "2", "%\nO2\n%\n")
    {:ok, _} = Library.store(lib, "3", "%\nO3\n%\n")

    {:ok, c} = Library.compare(lib)
    assert c.read_at == nil
    assert Enum.all?(c.programs, &(&1.on_machine == :unknown))

    entries = %{
      "000001.PRO" => Vws.Links.DNC.Report.entry("000001.PRO", a1),
      "000002.PRO" => Vws.Links.DNC.Report.entry("000002.PRO", "%\nO2\nX\n%\n"),
      "000009.PRO" => Vws.Links.DNC.Report.entry("000009.PRO", "%\nO9\n%\n")
    }

    :ok = Library.record_machine(lib, entries)
    {:ok, c} = Library.compare(lib)
    assert %DateTime{} = c.read_at

    assert Map.new(c.programs, &{&1.name, &1.on_machine}) ==
             %{"000001.PRO" => {:same, 1}, "000002.PRO" => :differs, "000003.PRO" => :absent}

    assert c.machine_only == ["000009.PRO"]
    assert Vws.Ops.LibraryText.on_machine_text({:same, 1}, 2) =~ "v1"
  end

  test "a workstation's library outlives it: stopped and started again, every version is there",
       %{dir: dir} do
    id = "lib-restart-#{System.unique_integer([:positive])}"
    %{sup: sup} = Vws.Test.Workstation.start(id: id, library: dir)
    assert Library.dir(id) == {:ok, dir}
    {:ok, _} = Library.store(id, "8", "%\nO8\nN1\n%\n", source: "iex")
    {:ok, _} = Library.store(id, "8", "%\nO8\nN2\n%\n", source: "wc")
    ref = Process.monitor(sup)
    :ok = stop_supervised({Vws.CEC.Workstation, id})
    assert_receive {:DOWN, ^ref, :process, _, _}, 5_000
    # (the registry forgets a dead process a moment after it died)
    assert Vws.Test.Eventually.eventually(fn -> Library.dir(id) == {:error, :no_library} end)

    Vws.Test.Workstation.start(id: id, library: dir)
    {:ok, [p]} = Library.list(id)
    assert Enum.map(p.versions, &{&1.version, &1.source}) == [{1, "iex"}, {2, "wc"}]
    assert {:ok, "%\nO8\nN1\n%\n", _} = Library.read(id, "8", 1)
    {:ok, v} = Library.store(id, "8", "%\nO8\nN3\n%\n")
    assert v.version == 3
  end

  test "property: any name is a GE-2000 file name or refused, and a store never writes outside " <>
         "the library directory",
       %{lib: lib, dir: dir} do
    parts =
      :proper_types.oneof([
        ~c"..",
        ~c"/",
        ~c".",
        ~c"~",
        ~c"PRO",
        ~c"gsu",
        ~c"O",
        ~c"0",
        ~c"12",
        ~c"\0"
      ])

    name =
      :proper_types.list(
        :proper_types.oneof([parts, :proper_types.list(:proper_types.range(0, 255))])
      )

    property =
      :proper.forall(name, fn chunks ->
        text = chunks |> List.flatten() |> :erlang.list_to_binary()

        case Library.name(text) do
          {:ok, n} ->
            n =~ ~r/^\d{6}\.(PRO|GSU)$/ and match?({:ok, _}, Library.store(lib, text, "x"))

          {:error, :bad_name} ->
            Library.store(lib, text, "x") == {:error, :bad_name}
        end
      end)

    assert_property(property, 300)
    # everything stored is inside the directory, and only under version names
    parent = Path.dirname(dir)

    # one store for sure (a run whose generated names were all refused stored nothing)
    {:ok, _} = Library.store(lib, "1", "x")

    assert Path.wildcard(Path.join(parent, "*"))
           |> Enum.filter(&String.starts_with?(&1, dir))
           |> Kernel.--([dir]) == []

    {:ok, files} = File.ls(dir)
    assert Enum.all?(files, &(&1 == ".v" or &1 =~ ~r/^\d{6}\.(PRO|GSU)~\d{6}~/))
  end

  describe "versions from the machine (issue 30 item 6)" do
    test "are never what :latest names; they are read by number, released as a new version",
         %{lib: lib} do
      {:ok, _} = Library.store(lib, "10", "%\nO10\nN1\n%\n", source: "wc")
      edited = "%\nO10\nN1 (EDITED AT THE PANEL)\n%\n"
      {:ok, m} = Library.store(lib, "10", edited, source: "from the machine")
      assert {m.version, m.released, m.origin} == {2, false, :machine}

      assert {:ok, "%\nO10\nN1\n%\n", %{version: 1}} = Library.read(lib, "10")
      assert {:ok, ^edited, %{version: 2}} = Library.read(lib, "10", 2)
      assert {:ok, %{version: 2}} = Library.version(lib, "10", :newest)
      # export and diff take :latest the same way
      {:ok, diff} = Library.diff(lib, "10", :latest, 2)
      assert "+ N1 (EDITED AT THE PANEL)" in Vws.Ops.LibraryText.format_diff(diff)

      # only from the machine: nothing released
      {:ok, _} = Library.store(lib, "11", "%\nO11\n%\n", source: "from the machine")
      assert Library.read(lib, "11") == {:error, :not_released}

      # released: a new version with its bytes, which :latest names
      {:ok, r} = Library.release(lib, "10", 2, source: "cli")

      assert {r.version, r.source, r.released, r.digest} ==
               {3, "cli release of v2", true, m.digest}

      assert {:ok, ^edited, %{version: 3}} = Library.read(lib, "10")
      # released again: the latest released already holds these bytes, nothing stored
      assert {:ok, %{version: 3}} = Library.release(lib, "10", 2)
      assert {:ok, [_, _, _]} = Library.versions(lib, "10")
      assert {:ok, %{version: 2, released: true}} = Library.release(lib, "11", 1)
    end

    test "the compare and its words say which version came from the machine", %{lib: lib} do
      a = "%\nO12\nN1\n%\n"
      b = "%\nO12\nN2\n%\n"
      {:ok, _} = Library.store(lib, "12", a, source: "wc")
      {:ok, _} = Library.store(lib, "12", b, source: "from the machine")
      {:ok, _} = Library.store(lib, "13", "%\nO13\n%\n", source: "from the machine")
      :ok = Library.record_machine(lib, %{"000012.PRO" => Vws.Links.DNC.Report.entry("x", b)})

      {:ok, c} = Library.compare(lib)
      [p12, p13] = c.programs
      assert {p12.latest.version, p12.newest.version, p12.on_machine} == {1, 2, {:same, 2}}
      assert {p13.latest, p13.newest.version} == {nil, 1}
      text = Enum.join(Vws.Ops.LibraryText.format_compare(c), "\n")

      assert text =~
               ~r/000012.PRO  v1 of 2 .* on the machine: same as v2 \(from the machine, not released\)  \(newer, from the machine, not released: v2\)/

      assert text =~ ~r/000013.PRO  v1 of 1 \(from the machine, not released\) .* absent/
    end
  end

  describe "versions are told apart by content (issue 30 item 7)" do
    test "two programs of one size and CRC-16 are two versions; the directory cannot tell " <>
           "which the machine holds",
         %{lib: lib} do
      [a, b] = Vws.Test.CRCCollision.programs(14, 2)
      {:ok, v1} = Library.store(lib, "14", a, source: "wc", only_if_changed: true)
      # not "the same program again": the digest differs, size and CRC do not
      {:ok, v2} = Library.store(lib, "14", b, source: "wc", only_if_changed: true)
      assert {v1.size, v1.crc} == {v2.size, v2.crc}
      assert {v1.version, v2.version} == {1, 2} and v1.digest != v2.digest
      # the very same bytes again are not a new version
      assert {:ok, %{version: 2}} = Library.store(lib, "14", b, only_if_changed: true)
      assert {:ok, ^a, _} = Library.read(lib, "14", 1)

      entry = Vws.Links.DNC.Report.entry("000014.PRO", a)
      {:ok, vs} = Library.versions(lib, "14")
      assert Library.on_machine(vs, entry) == {:ambiguous, [1, 2]}
      assert Vws.Ops.LibraryText.on_machine_text({:ambiguous, [1, 2]}, 2) =~ "read back to tell"
      assert Library.same_as(vs, Library.digest(a)) == {:ok, v1}
      assert Library.same_as(vs, Library.digest(b)) == {:ok, v2}
      assert Library.same_as(vs, Library.digest("%\nO14\n%\n")) == :none

      # a third version with v1's bytes: the same content, so the directory names it (the newest)
      {:ok, _} = Library.store(lib, "15", a)
      {:ok, _} = Library.store(lib, "15", a)
      {:ok, vs15} = Library.versions(lib, "15")
      assert Library.on_machine(vs15, entry) == {:same, 2}
    end

    test "a version whose file no longer has its digest reads as damaged", %{lib: lib, dir: dir} do
      [a, b] = Vws.Test.CRCCollision.programs(16, 2)
      {:ok, v} = Library.store(lib, "16", a)
      # same size, same CRC-16: only the digest sees it
      File.write!(Path.join(dir, v.file), b)
      assert Library.read(lib, "16") == {:error, :damaged}
      # and a store of the same bytes is a new version (the damaged one is not them)
      assert {:ok, %{version: 2}} = Library.store(lib, "16", a, only_if_changed: true)
    end

    test "a library stored before digests: each digest is computed from the bytes on load",
         %{lib: lib, dir: dir} do
      {:ok, v} = Library.store(lib, "17", "%\nO17\nN1\n%\n", source: "wc")
      # the version as it was named before digests: without its last field
      old = String.replace(v.file, ~r/~[0-9a-f]{64}$/, "")
      File.rename!(Path.join(dir, v.file), Path.join(dir, old))
      File.rm!(Path.join([dir, ".v", "000017.PRO~000001"]))
      File.ln_s!(Path.join("..", old), Path.join([dir, ".v", "000017.PRO~000001"]))

      assert {:ok, [p]} = Library.list(lib)
      assert [%{file: ^old, digest: digest}] = p.versions
      assert digest == v.digest
      assert {:ok, %{digest: ^digest}} = Library.version(lib, "17", 1)
      assert {:ok, "%\nO17\nN1\n%\n", _} = Library.read(lib, "17")

      assert {:ok, %{version: 1}} =
               Library.store(lib, "17", "%\nO17\nN1\n%\n", only_if_changed: true)

      {:ok, v2} = Library.store(lib, "17", "%\nO17\nN2\n%\n")
      assert v2.file =~ ~r/~[0-9a-f]{64}$/
    end

    # up to 8 synced stores a case, each a few calls of the node's one file server: behind the
    # whole suite's disk traffic, 100 cases passed a minute (twice in six full runs)
    @tag timeout: 300_000
    test "property: every listed version's digest is that of its bytes; a version from the " <>
           "machine is never :latest; equal digests only for equal bytes",
         %{dir: dir} do
      [c1, c2, c3] = Vws.Test.CRCCollision.programs(1, 3)

      bytes =
        :proper_types.oneof([
          :proper_types.elements([c1, c2, c3]),
          :proper_types.binary(),
          :proper_types.elements(["%\nO1\n%\n", ""])
        ])

      source = :proper_types.elements(["wc", "cli", "from the machine"])
      # 1 to 8 stores a case: each store syncs to disk (several fsyncs), and lists of up to
      # PropEr's ~40 took over a minute under the whole suite's I/O
      stores =
        :proper_types.bind(
          :proper_types.integer(1, 8),
          &:proper_types.vector(&1, {bytes, source, :proper_types.bool()}),
          false
        )

      property =
        :proper.forall(stores, fn stores ->
          lib = {:dir, Path.join(dir, "p#{System.unique_integer([:positive])}")}

          for {b, src, dedupe} <- stores,
              do: {:ok, _} = Library.store(lib, "1", b, source: src, only_if_changed: dedupe)

          {:ok, [p]} = Library.list(lib)

          read =
            for v <- p.versions do
              {:ok, b, ^v} = Library.read(lib, "1", v.version)
              {v, b}
            end

          released = for {b, src, _} <- stores, src != "from the machine", do: b

          Enum.all?(read, fn {v, b} -> v.digest == Library.digest(b) end) and
            Enum.all?(for({v, b} <- read, {w, c} <- read, do: v.digest == w.digest == (b == c))) and
            case Library.read(lib, "1") do
              {:ok, b, v} -> v.released and released != [] and b == List.last(released)
              {:error, :not_released} -> released == []
            end
        end)

      assert_property(property, 100)
    end
  end
end
