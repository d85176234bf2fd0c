defmodule Mix.Tasks.Vws.ServeJournalTest do
  @moduledoc """
  Durability as a user meets it (issue 15): `mix vws.serve` in an OS process of its own, killed
  with SIGKILL (`kill -9`: nothing of it runs after, no journal closed, no socket shut), then
  started again on the same journal. The NC file, NC_UP and every command status come back.
  The first round trip (WC → CEC → GE-2000 → CEC → WC) goes through a relay that inverts a bit
  of every third transfer answer, both ways: the program still comes back byte-identical.
  """
  use ExUnit.Case, async: true

  alias Vws.Test.FlipRelay
  alias Vws.Peers.WC.Client

  @moduletag :tmp_dir
  @moduletag timeout: 300_000

  @program ["%", "O004711", "N10 G90 G00 X0 Y0", "N20 G01 X63.5 F200", "N30 M30", "%"]

  test "the NC file, NC_UP and every command status survive kill -9 of mix vws.serve",
       %{tmp_dir: dir} do
    journal = Path.join(dir, "journal")

    # before: a program downloaded to the CEC and on to the GE-2000, uploaded back into NC_UP
    {serve, wc} = serve!(journal)
    {:ok, relay} = FlipRelay.start_link(wc)
    counter = :counters.new(1, [])

    flip = fn line ->
      :counters.add(counter, 1, 1)
      if rem(:counters.get(counter, 1), 3) == 0, do: FlipRelay.flip(line, 5, 2), else: line
    end

    answer = ~r/^A\d{7}\r?$/

    :ok =
      FlipRelay.plan(relay, {:lines, [{:to_client, answer, flip}, {:to_target, answer, flip}]})

    {:ok, client} = Client.connect(FlipRelay.endpoint(relay))
    assert {:ok, {"M", 1}} = Client.download_program(client, @program)
    assert :done = Client.await_command(client, "M", 1, 30_000)
    assert {:ok, [{"M", 2}]} = Client.send_commands(client, [{"M", "DOWNLOAD_GE"}])
    assert :done = Client.await_command(client, "M", 2, 60_000)
    assert {:ok, [{"M", 3}]} = Client.send_commands(client, [{"M", "UPLOAD_GE(004711.PRO)"}])
    assert :done = Client.await_command(client, "M", 3, 60_000)
    assert {:ok, [{"G", 1}]} = Client.send_commands(client, [{"G", "ROTATE_45"}])

    assert {:error, %{data: %{status: "ERROR " <> _}}} =
             Client.await_command(client, "G", 1, 30_000)

    assert {:ok, {"M", 4}, @program} = Client.upload_program(client)
    assert :done = Client.await_command(client, "M", 4, 30_000)
    assert FlipRelay.counts(relay).flips >= 4

    statuses = statuses(client)
    assert statuses["MONARCH_CMD"] == "0004DONE"
    Client.close(client)

    kill_9!(serve)

    # after: the same journal, a new process; nothing of the old one remains. This time the
    # journal is named by VWS_JOURNAL_DIR (mix vws.serve ignored it), with VWS_WC set as a
    # release's environment would have it (mix vws.serve crashed already_started)
    {serve, wc} =
      serve!(journal, [], [
        {~c"VWS_WC", ~c"tcp://127.0.0.1:0"},
        {~c"VWS_JOURNAL_DIR", to_charlist(journal)}
      ])

    {:ok, client} = Client.connect(wc, sequence: 500, numbers: %{"M" => 10})
    assert statuses(client) == statuses

    # NC_UP came back: UPLOAD_SUN sends it
    assert {:ok, {"M", 10}, @program} = Client.upload_program(client)
    assert :done = Client.await_command(client, "M", 10, 30_000)

    # the NC file came back: the (new, empty) GE-2000 gets it and holds exactly its bytes
    assert {:ok, [{"M", 11}]} = Client.send_commands(client, [{"M", "DOWNLOAD_GE"}])
    assert :done = Client.await_command(client, "M", 11, 60_000)
    Client.close(client)
    kill_9!(serve)
  end

  defp statuses(client) do
    for name <- ~w(ROBOT_CMD MONARCH_CMD GRIPPER_CMD FIXTURE_CMD VACUUM_CMD HYDRAULIC_CMD),
        into: %{} do
      {:ok, text} = Client.status(client, name)
      {name, text}
    end
  end

  # `mix vws.serve` on free ports with the journal in `journal`; returns the port and where
  # SUN_COMM serves the WC.
  defp serve!(journal, args \\ nil, env \\ [{~c"VWS_WC", false}, {~c"VWS_JOURNAL_DIR", false}]) do
    args = args || ["--journal", journal]

    port =
      Port.open({:spawn_executable, System.find_executable("mix")}, [
        :binary,
        :exit_status,
        :stderr_to_stdout,
        {:line, 4096},
        args: ~w(vws.serve --id J15 --wc tcp://127.0.0.1:0 --http-port 0 --time-scale 20) ++ args,
        env:
          [{~c"MIX_ENV", ~c"test"}, {~c"VWS_DATA_DIR", to_charlist(Path.dirname(journal))}] ++ env
      ])

    {:os_pid, os_pid} = Port.info(port, :os_pid)

    on_exit(fn ->
      System.cmd("kill", ["-9", Integer.to_string(os_pid)], stderr_to_stdout: true)
    end)

    wc = await_line(port, ~r/SUN_COMM waits for the WC on (tcp:\S+)/, "")
    assert await_line(port, ~r/^Journal: (.*)$/, "") == journal
    {{port, os_pid}, wc}
  end

  defp await_line(port, regex, seen) do
    receive do
      {^port, {:data, {_eol, line}}} ->
        case Regex.run(regex, line, capture: :all_but_first) do
          [value] -> value
          nil -> await_line(port, regex, seen <> line <> "\n")
        end

      {^port, {:exit_status, status}} ->
        flunk("mix vws.serve exited #{status}:\n#{seen}")
    after
      120_000 -> flunk("mix vws.serve did not say #{inspect(regex)}:\n#{seen}")
    end
  end

  defp kill_9!({port, os_pid}) do
    {_, 0} = System.cmd("kill", ["-9", Integer.to_string(os_pid)])
    assert_receive {^port, {:exit_status, status}}, 30_000
    assert status in [137, 9]
  end
end
