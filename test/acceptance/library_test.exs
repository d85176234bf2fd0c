defmodule Vws.Acceptance.LibraryTest do
  # The program library as a user meets it (issue 18): `mix vws.serve` in an OS process, a WC
  # over real TCP, and `mix vws.library` as OS processes of their own on the same data directory
  # — while the workstation runs and after it stopped; and a store killed with kill -9.
  use ExUnit.Case, async: true

  alias Vws.CEC.Library
  alias Vws.Test.Acceptance
  alias Vws.Peers.WC.Client

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 300_000

  @program ["%", "O4711 (LIBRARY)", "N10 G90 G00 X0 Y0", "N20 G01 X63.5 F200", "N30 M30", "%"]

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp env(data), do: [{"MIX_ENV", "dev"}, {"VWS_DATA_DIR", data}]

  # `mix vws.library ARGS` to its end: {exit status, output}
  defp library(data, args) do
    Acceptance.run(["mix", "vws.library" | args], env: env(data))
  end

  defp command(client, text) do
    {:ok, [{"M", n}]} = Client.send_commands(client, [{"M", text}])
    Client.await_command(client, "M", n, 60_000)
  end

  test "DOWNLOAD_HP fills the library of a running workstation; mix vws.library lists, compares, " <>
         "imports, diffs and exports, running or stopped",
       %{tmp_dir: data} do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    serve =
      Acceptance.serve(~w(--wc-port #{wc} --http-port #{http} --time-scale 20), env: env(data))

    lib_dir = Path.join([data, "library", "VWS"])
    Acceptance.await(serve, ~r/Program library: #{Regex.escape(lib_dir)}/)

    {:ok, client} = Client.connect("tcp://127.0.0.1:#{wc}")
    assert {:ok, {"M", n}} = Client.download_program(client, @program)
    assert :done = Client.await_command(client, "M", n, 30_000)
    assert :done = command(client, "DOWNLOAD_GE")

    {0, out} = library(data, ["list"])
    assert out =~ ~r/machine directory read \d{4}-/

    assert out =~
             ~r/004711\.PRO  v1 of 1  \S+  wc  \d+ bytes  CRC [0-9A-F]{4}  on the machine: same$/m

    # a second version from the command line, while the workstation runs
    file = Path.join(data, "part.nc")

    File.write!(
      file,
      Vws.Links.DNC.Program.to_text(List.replace_at(@program, 3, "N20 G01 X70.0 F200"))
    )

    {0, out} = library(data, ["import", file])
    assert out =~ "stored 004711.PRO v2"
    {0, out} = library(data, ["compare"])
    assert out =~ "004711.PRO  v2 of 2"
    assert out =~ "on the machine: same as v1 (not the latest)"

    # the WC sends the library's latest version by name; the machine holds it
    assert :done = command(client, "DOWNLOAD_GE(004711.PRO)")
    assert :done = command(client, "COMPARE_GE(004711.PRO)")
    {0, out} = library(data, ["show", "004711.PRO"])
    assert out =~ ~r/v2 .* cli .*<- on the machine/

    # the machine loses the program: the recorded directory is stale until refreshed
    assert :done = command(client, "PROGRAM_DELETE(004711.PRO)")
    {0, out} = library(data, ["compare"])
    assert out =~ "on the machine: same"
    # (the WC leaves the link first: the CLI is the WC for a moment, as mix vws.wc is)
    Client.close(client)
    {0, out} = library(data, ["compare", "--refresh", "--endpoint", "tcp://127.0.0.1:#{wc}"])
    assert out =~ "004711.PRO  v2 of 2"
    assert out =~ "on the machine: absent"

    # the dashboard shows the same, in a browser
    if Vws.Test.Browser.chromium() do
      text = dashboard_text("http://127.0.0.1:#{http}/")
      assert text =~ "Program library"
      assert text =~ ~r/1 programs, 2 versions — on the machine: 0 same, 0 differ, 1 absent/
      assert text =~ ~r/004711\.PRO\s+2\s+v2\s+\S+\s+cli\s+\d+\s+[0-9A-F]{4}\s+absent/
    end

    # stopped: the library is all on disk
    Acceptance.signal(serve, "TERM")
    assert Acceptance.await_exit(serve) == 0

    {0, out} = library(data, ["diff", "004711.PRO", "1", "2"])
    assert out =~ ~r/^- N20 G01 X63.5 F200$/m
    assert out =~ ~r/^\+ N20 G01 X70.0 F200$/m
    out_file = Path.join(data, "v1.nc")
    {0, _} = library(data, ["export", "004711.PRO", out_file, "--version", "1"])
    assert File.read!(out_file) == Vws.Links.DNC.Program.to_text(@program)
    {1, out} = library(data, ["show", "../../etc/passwd"])
    assert out =~ "not a program name"
    {2, _} = library(data, ["frobnicate"])
  end

  test "an OS process killed with kill -9 while storing leaves only whole versions", %{
    tmp_dir: data
  } do
    lib_dir = Path.join(data, "lib")

    # about 970 KB: as large as the GE-2000 stores (999,999 bytes, PROTOCOLS.md §2; the library
    # keeps larger ones for drip feeds), so that the kill lands while one is being written
    big = String.duplicate("N10 G01 X1.0 Y2.0 F300\n", 42_000)

    code = """
    text = "%\\nO42\\n" <> String.duplicate("N10 G01 X1.0 Y2.0 F300\\n", 42_000) <> "%\\n"
    for i <- Stream.iterate(1, &(&1 + 1)) do
      {:ok, v} = Vws.CEC.Library.store({:dir, #{inspect(lib_dir)}}, "42", text, source: "cli")
      IO.puts("stored v\#{v.version}")
    end
    """

    proc = Acceptance.start(["mix", "run", "--no-start", "-e", code], env: env(data))
    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/stored v3/, 120_000)
    {_, 0} = System.cmd("kill", ["-9", Integer.to_string(Acceptance.os_pid(proc))])
    Acceptance.await_exit(proc)

    {:ok, versions} = Library.versions({:dir, lib_dir}, "42")
    assert length(versions) >= 3

    for v <- versions do
      assert {:ok, text, _} = Library.read({:dir, lib_dir}, "42", v.version)
      assert text == "%\nO42\n" <> big <> "%\n"
    end

    # and the library takes the next version as if nothing happened
    {0, out} = library(data, ["--library", lib_dir, "import", "--name", "42", write(data)])
    assert out =~ ~r/stored 000042\.PRO v\d+/
  end

  # The dashboard's visible text after the page ran 3 s in headless Chromium.
  # (all whitespace one blank: the table's cells on one line)
  defp dashboard_text(url) do
    dom = Vws.Test.Browser.page(url)

    dom
    |> String.replace(~r{<script.*?</script>}s, "")
    |> String.replace(~r{<style.*?</style>}s, "")
    |> String.replace(~r{<[^>]+>}, " ")
    |> String.replace("&amp;", "&")
    |> String.replace(~r/\s+/, " ")
  end

  defp write(data) do
    path = Path.join(data, "p42.nc")
    File.write!(path, "%\nO42\nN1\n%\n")
    path
  end
end
