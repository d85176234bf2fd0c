defmodule Vws.Codecs.WC.CLITest do
  # The command-line WC (mix vws.wc, bin/vws-wc) against a workstation on real TCP.
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.Peers.WC.CLI

  setup do
    %{ws: ws} =
      Vws.Test.Workstation.start(
        wc: "tcp://127.0.0.1:0",
        partitions: [vacuum: [module: Vws.Test.ObedientPartition, interlocks: :off, link: :test]]
      )

    endpoint =
      "tcp://#{Vws.CEC.SunComm.listening(ws) |> to_string() |> String.replace_prefix("tcp://", "")}"

    %{ws: ws, endpoint: endpoint}
  end

  defp cli(args) do
    me = self()
    # (usage errors go to standard error)
    out =
      capture_io(fn ->
        capture_io(:stderr, fn -> send(me, {:status, CLI.main(args)}) end)
      end)

    assert_received {:status, status}
    {status, out}
  end

  test "--status prints the status; exit 0", %{endpoint: e} do
    assert {0, "0000NONE\n"} = cli(["--endpoint", e, "--status", "VACUUM_CMD", "--quiet"])
  end

  test "--command runs a command to its end: DONE is 0, ERROR is 1 with the CEC's reason; a second run is a new command",
       %{endpoint: e} do
    assert {0, out} = cli(["--endpoint", e, "--command", "V ON"])
    assert out =~ "V0001 ON: DONE"
    assert {0, out} = cli(["--endpoint", e, "--command", "V ON"])
    assert out =~ "V0002 ON: DONE"

    # no VAL II link: the CEC's own answer
    assert {1, out} = cli(["--endpoint", e, "--command", "R WHERE"])
    assert out =~ "R0001 WHERE: ERROR NO LINK TO VAL II"
  end

  test "--send frames a string without its BCC and prints the reply; E is 1", %{endpoint: e} do
    assert {0, out} = cli(["--endpoint", e, "--send", "*0001*S0001ROBOT_CMD*"])
    assert out =~ "→ *0001*S0001ROBOT_CMD*012"
    assert out =~ ~r/← \d\dS00010000NONE\d{3}/
    assert {1, out} = cli(["--endpoint", e, "--send", "*0002*S0002ROBOT_CMD*000"])
    assert out =~ "← E"
  end

  @tag :tmp_dir
  test "--script runs a cycle script; a stopped script is 1", %{endpoint: e, tmp_dir: dir} do
    ok = Path.join(dir, "ok.vws")
    File.write!(ok, "V ON\nV OFF\n")
    bad = Path.join(dir, "bad.vws")
    File.write!(bad, "V ON\nR WHERE\nV OFF\n")
    assert {0, out} = cli(["--endpoint", e, "--script", ok])
    assert out =~ "result:          COMPLETED"
    assert {1, out} = cli(["--endpoint", e, "--script", bad])
    assert out =~ ~r/result: +STOPPED at line 2 .*ERROR NO LINK TO VAL II/
  end

  test "usage errors and an unreachable controller are 2" do
    assert {2, _} = cli(["--status"])
    assert {2, _} = cli(["--command", "X FOO"])
    assert {2, _} = cli(["--status", "A", "--command", "V ON"])
    port = Vws.Test.Acceptance.free_port()
    assert {2, out} = cli(["--endpoint", "tcp://127.0.0.1:#{port}", "--status", "ROBOT_CMD"])
    assert out =~ "cannot reach the controller"
  end

  test "a bad flag is one line naming it and what is wrong (Vws.CLIOptions), status 2" do
    me = self()

    err =
      capture_io(:stderr, fn ->
        capture_io(fn -> send(me, {:status, CLI.main(["--status", "X", "--timeout", "soon"])}) end)
      end)

    assert_received {:status, 2}
    assert err =~ "--timeout: soon is not a whole number above 0"
    refute err =~ ~r/[{}]/

    err =
      capture_io(:stderr, fn ->
        capture_io(fn -> CLI.main(["--bcc", "crc", "--status", "X"]) end)
      end)

    assert err =~ "--bcc: crc is not one of sum, xor"
  end
end
