defmodule Vws.Acceptance.IexServeTest do
  # `iex -S mix vws.serve` as the README runs it: in a terminal (tmux), with the shell used while
  # the simulated floor keeps serving, and stopped with one Ctrl-C in order (Vws.Ops.Signals:
  # the terminal sends SIGQUIT for it while the node runs, never the BEAM's BREAK menu).
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 180_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  # The exit status; if the node does not stop in time, the failure message says what the pane's
  # process is doing (ps) and, from a crash dump (SIGUSR1), where its Erlang processes wait.
  defp exit_or_dump(t, dump) do
    Acceptance.tmux_await_exit(t, 60_000)
  rescue
    error in ExUnit.AssertionError ->
      pid = Acceptance.tmux_pid(t)

      {ps, _} =
        System.cmd(
          "sh",
          [
            "-c",
            "ps -o pid,pgid,stat,wchan:24,cmd -s #{pid}; grep -E 'State|Sig' /proc/#{pid}/status"
          ],
          stderr_to_stdout: true
        )

      System.cmd("kill", ["-s", "USR1", "--", "#{Acceptance.tmux_pid(t)}"], stderr_to_stdout: true)

      Vws.Test.Eventually.eventually(fn -> File.exists?(dump) end, 30_000, 200)
      Process.sleep(2_000)

      waiting =
        case File.read(dump) do
          {:ok, text} ->
            text
            |> String.split("\n=proc:")
            |> Enum.filter(&(&1 =~ ~r/^State: Waiting/m and not (&1 =~ "gen_server:loop")))
            |> Enum.map_join(
              "\n",
              &(&1 |> String.split("\n") |> Enum.take(12) |> Enum.join(" | "))
            )

          {:error, reason} ->
            "no crash dump: #{inspect(reason)}"
        end

      reraise %{error | message: error.message <> "\n#{ps}\nprocesses waiting:\n" <> waiting},
              __STACKTRACE__
  end

  @tag :tmux
  test "iex -S mix vws.serve: the shell works and the floor keeps serving; one Ctrl-C stops it in order" do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    dump = Path.join(System.tmp_dir!(), "vws-iex-#{System.unique_integer([:positive])}.dump")
    on_exit(fn -> File.rm(dump) end)

    t =
      Acceptance.tmux_start(
        "iex -S mix vws.serve --wc-port #{wc} --http-port #{http} --time-scale 20",
        env: [{"MIX_ENV", "dev"}, {"ERL_CRASH_DUMP", dump}]
      )

    on_exit(fn -> Acceptance.tmux_stop(t) end)

    Acceptance.tmux_await(t, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    Acceptance.tmux_await(t, ~r/iex\(1\)>/)

    # the shell is the user's: inspecting the workstation from it
    # (a prompt again after it: the shell answered, whatever overview printed — its content is
    # the dashboard/inspect tests' business)
    Acceptance.tmux_send(t, ~s|Vws.Ops.Inspect.overview("VWS")|)
    Acceptance.tmux_await(t, ~r/overview\("VWS"\)\n[\s\S]*iex\(\d+\)> *$/m)

    # the mix task's process has ended (the shell runs); the floor it started must not have
    # ended with it: a command verified on the simulated sensors (DAQ #1) still completes
    assert Acceptance.wc_request(wc, "*0001*F0001OPEN*") =~ ~r/^05A0001\d{3}$/
    deadline = System.monotonic_time(:millisecond) + 30_000
    reply = Acceptance.await_command(wc, "FIXTURE_CMD", 2, 1, deadline)
    assert reply =~ ~r/^\d\dS\d{4}0001DONE\d{3}$/, "#{reply}\n#{Acceptance.tmux_capture(t)}"

    refute Acceptance.tmux_capture(t) =~ "DAQ #1 NOT CONNECTED"

    # one Ctrl-C (SIGQUIT while the node has the terminal): a clean stop, in order, status 0
    Acceptance.tmux_keys(t, ["C-c"])
    Acceptance.tmux_await(t, ~r/SIGQUIT received \(Ctrl-C\)/, 30_000)
    assert exit_or_dump(t, dump) == 0
    pane = Acceptance.tmux_capture(t)
    assert [_, stop] = String.split(pane, "SIGQUIT received", parts: 2), pane
    refute stop =~ ~r/\*\* \(EXIT|SUPERVISOR REPORT|CRASH REPORT|unknown registry|\[error\]/, pane
  end
end
