defmodule Vws.Acceptance.LibraryWorkflowTest do
  # Issue 27 as a user meets it: `mix vws.serve` in an OS process with its simulated GE-2000, a
  # WC over real TCP, `mix vws.library` as OS processes of their own — a draft refused and
  # FORCEd, the line diff against what the machine holds, the transfer history on the command
  # line and the dashboard (headless Chromium), kept across a kill -9 and a restart.
  use ExUnit.Case, async: true

  alias Vws.Peers.WC.Client
  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 400_000

  @program ["%", "O4711 (LIBRARY)", "N10 G90 G00 X0 Y0", "N20 G01 X63.5 F200", "N30 M30", "%"]

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp env(data), do: [{"MIX_ENV", "dev"}, {"VWS_DATA_DIR", data}]

  defp library(data, args) do
    Acceptance.run(["mix", "vws.library" | args], env: env(data))
  end

  defp serve(data, wc, http) do
    Acceptance.serve(~w(--wc-port #{wc} --http-port #{http} --time-scale 20), env: env(data))
  end

  defp command(client, text) do
    {:ok, [{"M", n}]} = Client.send_commands(client, [{"M", text}])

    case Client.await_command(client, "M", n, 60_000) do
      :done -> "DONE"
      {:error, %{reason: :command_failed, data: %{status: status}}} -> status
    end
  end

  test "draft and FORCE, diff --machine, history on the command line and the dashboard, " <>
         "kept across kill -9",
       %{tmp_dir: data} do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()
    serve = serve(data, wc, http)

    {:ok, client} = Client.connect("tcp://127.0.0.1:#{wc}")
    assert {:ok, {"M", n}} = Client.download_program(client, @program)
    assert :done = Client.await_command(client, "M", n, 30_000)
    assert command(client, "DOWNLOAD_GE(004711.PRO)") == "DONE"

    # a draft from the command line, with a comment: not sent unless the WC says FORCE
    file = Path.join(data, "part.nc")

    File.write!(
      file,
      Vws.Links.DNC.Program.to_text(List.replace_at(@program, 3, "N20 G01 X70.0 F200"))
    )

    {0, out} = library(data, ["import", file, "--draft", "--comment", "X70 trial"])
    assert out =~ "stored 004711.PRO v2"
    assert command(client, "DOWNLOAD_GE(004711.PRO)") == "DONE"

    assert command(client, "DOWNLOAD_GE(004711.PRO/2)") ==
             "ERROR 004711.PRO VERSION 2 NOT RELEASED"

    assert command(client, "DOWNLOAD_GE(004711.PRO/2/FORCE)") == "DONE"

    # the line diff: the library's v1 against what the machine holds (v2), read back over DNC
    Client.close(client)
    endpoint = "tcp://127.0.0.1:#{wc}"

    {0, out} =
      library(data, ["diff", "--machine", "004711.PRO", "--version", "1", "--endpoint", endpoint])

    assert out =~ ~r/^--- 004711\.PRO v1 \(library\)$/m
    assert out =~ ~r/^- N20 G01 X63\.5 F200$/m
    assert out =~ ~r/^\+ N20 G01 X70\.0 F200$/m

    # a program the machine does not hold: ERROR in words, no diff
    File.write!(file, "%\nO4712\nN10 M30\n%\n")
    {0, _} = library(data, ["import", file])
    {1, out} = library(data, ["diff", "--machine", "4712", "--endpoint", endpoint])
    assert out =~ "ERROR PROGRAM ABSENT 004712.PRO"
    refute out =~ ~r/^[-+] /m

    {0, out} = library(data, ["history", "004711.PRO"])
    lines = String.split(out, "\n", trim: true)
    assert length(lines) == 4
    # newest first: the compare's read-back, the FORCEd draft, two downloads of v1
    assert Enum.at(lines, 0) =~
             ~r/004711\.PRO v2  from machine  COMPARE_GE\(004711\.PRO\) .* DONE  by WC string \d{4} M\d{4}  — same as v2$/

    assert Enum.at(lines, 1) =~
             ~r/004711\.PRO v2  to machine  DOWNLOAD_GE\(004711\.PRO\/2\/FORCE\) .* DONE/

    assert Enum.at(lines, 3) =~
             ~r/004711\.PRO v1  to machine  DOWNLOAD_GE\(004711\.PRO\)  \d+ bytes 1 blocks/

    if Vws.Test.Browser.chromium() do
      text = dashboard_text("http://127.0.0.1:#{http}/")
      assert text =~ "Transfer history (newest first)"

      assert text =~
               ~r/004711\.PRO v2 from machine COMPARE_GE\(004711\.PRO\) \d+ \d+ \d+ \d+ 0 DONE WC string \d{4} M\d{4} same as v2/
    end

    # killed with kill -9, started again on the same data: the history is all there, and grows
    {_, 0} = System.cmd("kill", ["-9", Integer.to_string(Acceptance.os_pid(serve))])
    Acceptance.await_exit(serve)
    serve = serve(data, wc, http)
    {:ok, client} = Client.connect(endpoint)
    assert command(client, "DOWNLOAD_GE(004711.PRO)") == "DONE"
    Client.close(client)
    Acceptance.signal(serve, "TERM")
    assert Acceptance.await_exit(serve) == 0

    {0, out} = library(data, ["history", "004711.PRO"])
    [newest | rest] = String.split(out, "\n", trim: true)
    assert rest == lines
    assert newest =~ ~r/004711\.PRO v1  to machine  DOWNLOAD_GE\(004711\.PRO\) .* DONE/
  end

  # the dashboard's visible text after 3 s of page time, all whitespace one blank
  defp dashboard_text(url),
    do:
      url
      |> Vws.Test.Browser.page()
      |> Vws.Test.Browser.text()
      |> String.replace(~r/\s+/, " ")
end
