defmodule Vws.Acceptance.LibraryImportTest do
  # `mix vws.library import` as a user runs it, an OS process on a data directory of its own:
  # a Python file is refused with the reason and exit status 1, nothing stored; a program is
  # stored once — importing the same file again stores nothing and says which version it is.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 300_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp library(data, args) do
    proc =
      Acceptance.start(["mix", "vws.library" | args],
        env: [{"MIX_ENV", "dev"}, {"VWS_DATA_DIR", data}]
      )

    status = Acceptance.await_exit(proc, 120_000)
    {status, Acceptance.output(proc)}
  end

  test "import refuses a Python file and a binary one with the reason; a copy of the latest version is not stored again",
       %{tmp_dir: data} do
    script = Path.join(data, "tool.py")
    File.write!(script, "import os\nprint(os.listdir(':1'))\n")
    {1, out} = library(data, ["import", script])
    assert out =~ "#{script}: not an NC program: its first line is not %"

    binary = Path.join(data, "part.nc")
    File.write!(binary, "%\nO1234\n" <> <<0, 159, 146, 150>> <> "\n%\n")
    {1, out} = library(data, ["import", binary])
    assert out =~ "not an NC program: a binary file (not text at byte 8)"

    {0, out} = library(data, ["list"])
    refute out =~ ".PRO"

    {0, out} = library(data, ["import", "priv/sims/programs/001234.nc"])
    assert out =~ ~r/^stored 001234\.PRO v1 /m
    {0, out} = library(data, ["import", "priv/sims/programs/001234.nc"])
    assert out =~ "priv/sims/programs/001234.nc: same as 001234.PRO v1, nothing stored"

    {0, out} = library(data, ["list"])
    assert out =~ ~r/001234\.PRO  v1 of 1 /
  end
end
