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
end
