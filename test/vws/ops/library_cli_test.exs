defmodule Vws.Ops.LibraryCLITest do
  # `mix vws.library` (Vws.Ops.LibraryCLI) on a library directory: versions from the machine are
  # shown as such, and released with `release`.
  use ExUnit.Case, async: true
  import ExUnit.CaptureIO

  alias Vws.CEC.Library
  alias Vws.Ops.LibraryCLI

  doctest Vws.Ops.LibraryText

  defp cli(args) do
    # (standard error: the messages of a usage error or a version not found)
    {{status, out}, _err} = with_io(:stderr, fn -> with_io(fn -> LibraryCLI.main(args) end) end)
    {status, out}
  end

  @tag :tmp_dir
  test "show and list mark versions from the machine; release makes one the latest released", %{
    tmp_dir: dir
  } do
    lib = {:dir, dir}
    {:ok, _} = Library.store(lib, "20", "%\nO20\nN1\n%\n", source: "wc")
    {:ok, m} = Library.store(lib, "20", "%\nO20\nN1 (PANEL)\n%\n", source: "from the machine")

    {0, out} = cli(["--library", dir, "show", "20"])
    assert out =~ ~r/v1  .* wc .* SHA-256 [0-9a-f]{16}… +<- latest released\n/
    assert out =~ ~r/v2  .* from the machine .*<- from the machine, not released\n/

    {0, out} = cli(["--library", dir, "list"])
    assert out =~ "000020.PRO  v1 of 2"
    assert out =~ "(newer, from the machine, not released: v2)"

    {0, out} = cli(["--library", dir, "release", "20", "2"])
    assert out =~ ~r/released 000020.PRO as v3 .* cli release of v2/
    assert {:ok, %{version: 3, digest: digest}} = Library.version(lib, "20")
    assert digest == m.digest

    {0, out} = cli(["--library", dir, "release", "20", "v2"])
    assert out =~ "v3, the latest released, already holds these bytes"

    assert {1, _} = cli(["--library", dir, "release", "20", "9"])
    assert {2, _} = cli(["--library", dir, "release", "20", "x"])
  end

  @tag :tmp_dir
  test "the workflow on the command line: import a draft with a comment, release, unrelease, " <>
         "comment, search, delete with a tombstone, history",
       %{tmp_dir: dir} do
    lib = {:dir, dir}
    {:ok, _} = Library.store(lib, "30", "%\nO30\nN1 G01 X1\n%\n", source: "wc")
    file = Path.join(dir, "p30.nc")
    File.write!(file, "%\nO30\nN1 G01 X2 (TRY SPINDLE 900)\n%\n")

    {0, out} = cli(["--library", dir, "import", file, "--draft", "--comment", "try X2"])
    assert out =~ "stored 000030.PRO v2"
    assert {:ok, %{version: 1}} = Library.version(lib, "30", :latest)

    {0, out} = cli(["--library", dir, "show", "30"])
    assert out =~ ~r/v1 .*<- latest released\n/
    assert out =~ ~r/v2 .*<- draft, not released\n +comment: try X2\n/

    {0, out} = cli(["--library", dir, "search", "spindle"])
    assert out =~ "000030.PRO v2  (text)  N1 G01 X2 (TRY SPINDLE 900)"
    {0, out} = cli(["--library", dir, "search", "TRY", "--in", "comment"])
    assert out == "000030.PRO v2  (comment)\n"
    {0, out} = cli(["--library", dir, "search", "30", "--in", "name"])
    assert out =~ "000030.PRO v1  (name)" and out =~ "000030.PRO v2  (name)"
    {1, ""} = cli(["--library", dir, "search", "nowhere"])
    {2, _} = cli(["--library", dir, "search", "x", "--in", "colour"])

    # released in place: no new version
    {0, _} = cli(["--library", dir, "release", "30", "2"])
    assert {:ok, %{version: 2, released: true, comment: "try X2"}} = Library.version(lib, "30")
    {0, out} = cli(["--library", dir, "unrelease", "30", "2"])
    assert out =~ "v2 is a draft"
    assert {:ok, %{version: 1}} = Library.version(lib, "30")
    {0, _} = cli(["--library", dir, "comment", "30", "1", "proven", "on", "part", "7"])
    assert {:ok, %{comment: "proven on part 7"}} = Library.version(lib, "30", 1)

    # deleted: gone from the versions, its number never given again, its tombstone shown
    {0, out} = cli(["--library", dir, "delete", "30", "2", "--why", "scrapped"])
    assert out =~ "deleted 000030.PRO v2"
    assert {:ok, [%{version: 1}]} = Library.versions(lib, "30")
    assert Library.version(lib, "30", 2) == {:error, :deleted}
    assert Library.read(lib, "30", 2) == {:error, :deleted}
    {0, out} = cli(["--library", dir, "show", "30"])
    assert out =~ ~r/v2  deleted \S+ by cli \(scrapped\)/
    {1, _} = cli(["--library", dir, "show", "30", "--version", "2"])
    assert {:ok, %{version: 3}} = Library.store(lib, "30", "%\nO30\nN3\n%\n")
    assert {:ok, [%{version: 2, deleted: %{source: "cli"}}]} = Library.tombstones(lib, "30")

    # the transfer history names the deleted version still
    :ok =
      Library.record_transfer(lib,
        program: "000030.PRO",
        version: 2,
        command: "DOWNLOAD_GE(000030.PRO/2/FORCE)",
        direction: "to machine",
        bytes: 30,
        blocks: 1,
        result: "DONE",
        requester: "WC string 0001 M0001"
      )

    {0, out} = cli(["--library", dir, "history", "30"])

    assert out =~
             ~r/000030.PRO v2  to machine  DOWNLOAD_GE\(000030.PRO\/2\/FORCE\)  30 bytes 1 blocks .* DONE  by WC string 0001 M0001/

    # the same lines in iex (Vws.Ops.Inspect.transfers/2, issue 27's "readable in iex")
    assert ExUnit.CaptureIO.capture_io(fn -> Vws.Ops.Inspect.transfers(lib, program: "30") end) ==
             out

    {0, "no transfers recorded\n"} = cli(["--library", dir, "history", "31"])
    {1, _} = cli(["--library", dir, "diff", "30", "--machine", "--cached"])
    {2, _} = cli(["--library", dir, "diff", "30"])
  end

  @tag :tmp_dir
  test "import and list a program over the 999,999 bytes the machine stores (kept for drip " <>
         "feeds); over what the library keeps, refused before it is read",
       %{tmp_dir: dir} do
    library = Path.join(dir, "library")
    # 1,500,024 bytes: over what the machine stores (Vws.Test.MonarchWC.long_program/1)
    text = Vws.Test.MonarchWC.long_program(88)
    file = Path.join(dir, "long.nc")
    File.write!(file, text)

    {0, out} = cli(["--library", library, "import", file])
    assert out =~ "stored 000088.PRO v1"
    {0, out} = cli(["--library", library, "list"])
    assert out =~ "000088.PRO  v1 of 1"
    {0, out} = cli(["--library", library, "show", "88"])
    assert out =~ "1500024 bytes"
    assert {:ok, ^text, %{size: 1_500_024}} = Library.read({:dir, library}, "88")
    # the same file again: nothing stored
    {0, out} = cli(["--library", library, "import", file])
    assert out =~ "same as 000088.PRO v1, nothing stored"

    # a (sparse) file larger than the library keeps
    huge = Path.join(dir, "huge.nc")
    {:ok, fd} = :file.open(String.to_charlist(huge), [:write, :binary])
    {:ok, _} = :file.position(fd, Library.max_bytes() + 1)
    :ok = :file.truncate(fd)
    :ok = :file.close(fd)
    args = ["--library", library, "import", huge]
    {{status, out}, err} = with_io(:stderr, fn -> with_io(fn -> LibraryCLI.main(args) end) end)
    assert status == 1

    assert out <> err =~
             "#{Library.max_bytes() + 1} bytes, more than the #{Library.max_bytes()} bytes the library keeps"

    assert {:ok, [%{versions: [_]}]} = Library.list({:dir, library})
  end

  @tag :tmp_dir
  test "a damaged state file makes its version a draft, said loudly", %{tmp_dir: dir} do
    lib = {:dir, dir}
    {:ok, _} = Library.store(lib, "40", "%\nO40\nN1\n%\n", source: "wc")
    {:ok, _} = Library.store(lib, "40", "%\nO40\nN2\n%\n", source: "wc", comment: "ok")
    path = Vws.CEC.Library.Workflow.path(dir, "000040.PRO", 2)
    bin = File.read!(path)
    File.write!(path, binary_part(bin, 0, byte_size(bin) - 20) <> "xxxxxxxxxxxxxxxxxxxx")

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        assert {:ok, %{version: 1}} = Library.version(lib, "40", :latest)
        assert {:ok, %{released: false}} = Library.version(lib, "40", 2)
      end)

    assert log =~ "the state of 000040.PRO v2 is damaged: taken as a draft"
  end
end
