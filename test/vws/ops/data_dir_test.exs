defmodule Vws.Ops.DataDirTest do
  use ExUnit.Case, async: true

  # journal_dir/2 with :default reads VWS_DATA_DIR / VWS_JOURNAL_DIR: the process environment
  # is the whole VM's, so those are tested through real OS processes
  # (test/mix/tasks/vws.serve_journal_test.exs, test/mix/tasks/vws.demo_test.exs)
  doctest Vws.Ops.DataDir

  test "a workstation id becomes one path segment under journal/ of the data directory" do
    dir = Vws.Ops.DataDir.journal_dir("../VWS 1/x", :default)

    if System.get_env("VWS_JOURNAL_DIR") in [nil, ""] do
      assert Path.basename(dir) == ".._VWS_1_x"
      assert Path.dirname(dir) == Path.join(Vws.Ops.DataDir.root(), "journal")
      assert Path.basename(Vws.Ops.DataDir.journal_dir("..", :default)) == "__"
    end
  end

  test "--journal and --no-journal exclude each other" do
    assert_raise ArgumentError, fn -> Vws.Ops.DataDir.choice(journal: "j", no_journal: true) end
  end
end
