defmodule Mix.Tasks.Vws.DemoTest do
  use ExUnit.Case, async: true

  # The task as a user runs it, in a VM of its own: its exit status is the point.
  @tag timeout: 300_000
  @tag :tmp_dir
  test "mix vws.demo --once prints the dialogue and a summary, and exits 0 only if it completed",
       %{tmp_dir: data} do
    {output, status} =
      System.cmd(
        System.find_executable("mix"),
        ~w(vws.demo --once --time-scale 50 --http-port 0),
        # the journal is on by default, in the data directory: this test's own
        env: [{"MIX_ENV", "test"}, {"VWS_DATA_DIR", data}, {"VWS_JOURNAL_DIR", nil}],
        stderr_to_stdout: true
      )

    assert File.exists?(Path.join([data, "journal", "VWS-DEMO"]))

    assert output =~ ~r{^dashboard and MTConnect agent: http://127\.0\.0\.1:\d+/ \(read-only\)$}m
    assert output =~ ~r/^ +\d+\.\d{3}s  → \*0001\*R0001DISABLE_TRAY1\*\d{3} /m
    assert output =~ ~r/^ +\d+\.\d{3}s  ← 05A0001\d{3} +ack: string 0001 received intact$/m
    assert output =~ "== Summary =="
    assert [result] = Regex.run(~r/^result: +(.*)$/m, output, capture: :all_but_first)

    if result == "COMPLETED" do
      assert status == 0
    else
      assert status != 0, output
      assert result =~ ~r/^STOPPED at line \d+ \(step \d+ of \d+\): \S/
    end
  end
end
