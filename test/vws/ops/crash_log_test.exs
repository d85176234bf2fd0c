defmodule Vws.Ops.CrashLogTest do
  # Issue 30 item 8: every crashed process is logged once with its reason, state machines
  # included — Elixir 1.14's Logger wrote nothing for a crashing :gen_statem (Vws.Ops.CrashLog).
  use ExUnit.Case, async: false

  import ExUnit.CaptureLog

  defmodule Machine do
    @behaviour :gen_statem
    def callback_mode, do: :handle_event_function
    def init(arg), do: {:ok, :idle, arg}
    def handle_event({:call, _from}, :boom, :idle, _data), do: raise("boom in the machine")
    def handle_event({:call, _from}, :stop, :idle, _data), do: {:stop, {:gave_up, 42}}
  end

  defmodule Server do
    use GenServer
    def init(arg), do: {:ok, arg}
    def handle_call(:boom, _from, _state), do: raise("boom in the server")
  end

  # lines opening a crash report in `log`
  defp crash_lines(log), do: Regex.scan(~r/^.*terminating$/m, log) |> List.flatten()

  defp crash(start, request) do
    Process.flag(:trap_exit, true)
    {:ok, pid} = start.()
    ref = Process.monitor(pid)
    catch_exit(:gen.call(pid, :"$gen_call", request))
    assert_receive {:DOWN, ^ref, :process, ^pid, _}
    # the report is written by the dying process before it goes; give Logger a moment to print
    Logger.flush()
    pid
  end

  test "a :gen_statem raising is logged once, with the exception, the module and the event" do
    log =
      capture_log(fn ->
        pid = crash(fn -> :gen_statem.start_link(Machine, %{}, []) end, :boom)
        send(self(), {:pid, pid})
      end)

    assert_received {:pid, pid}
    assert [line] = crash_lines(log), log
    assert line =~ ":gen_statem #{inspect(pid)} (#{inspect(Machine)}) terminating"
    assert log =~ "** (RuntimeError) boom in the machine"
    assert log =~ "Last event: {{:call, "
    assert log =~ ":boom}"
  end

  test "a :gen_statem stopping with a reason of its own is logged once, with the reason" do
    log = capture_log(fn -> crash(fn -> :gen_statem.start_link(Machine, %{}, []) end, :stop) end)
    assert [_line] = crash_lines(log), log
    assert log =~ "** (exit) {:gave_up, 42}"
  end

  test "a GenServer's crash is still logged once (not twice)" do
    log = capture_log(fn -> crash(fn -> GenServer.start_link(Server, %{}) end, :boom) end)
    assert [line] = crash_lines(log), log
    assert line =~ "GenServer"
    assert log =~ "** (RuntimeError) boom in the server"
  end

  test "SUN_COMM of a running workstation crashing: one log line with its reason" do
    log =
      capture_log(fn ->
        %{ws: ws} = Vws.Test.Workstation.start()
        sun = Vws.Names.whereis(ws, :sun_comm)
        ref = Process.monitor(sun)
        # its data made unusable from outside: the next call it answers crashes it
        :sys.replace_state(sun, fn {state, data} -> {state, Map.delete(data, :dialogue)} end)
        catch_exit(:gen_statem.call(sun, :dialogue))
        assert_receive {:DOWN, ^ref, :process, ^sun, {{:badkey, :dialogue, _}, _}}
        # restarted by its workstation
        assert Vws.Test.Eventually.eventually(fn ->
                 (Vws.Names.whereis(ws, :sun_comm) || sun) != sun
               end)

        Logger.flush()
      end)

    assert [line] = crash_lines(log), log
    assert line =~ ~r/^.*:gen_statem .* \(Vws\.CEC\.SunComm\.Server\) terminating$/
    assert log =~ "** (KeyError) key :dialogue not found"
  end

  # a process killed from outside writes nothing itself: its supervisor's report is the trace
  defp killed_lines(log), do: Regex.scan(~r/^.*was killed.*$/m, log) |> List.flatten()

  test "a supervised process killed from outside is logged once, by its supervisor's report" do
    log =
      capture_log(fn ->
        {:ok, sup} = Supervisor.start_link([{Agent, fn -> :state end}], strategy: :one_for_one)
        [{Agent, pid, _, _}] = Supervisor.which_children(sup)
        ref = Process.monitor(pid)
        Process.exit(pid, :kill)
        assert_receive {:DOWN, ^ref, :process, ^pid, :killed}
        # the supervisor restarted it: its report was written before
        assert Vws.Test.Eventually.eventually(fn ->
                 match?(
                   [{Agent, new, _, _}] when is_pid(new) and new != pid,
                   Supervisor.which_children(sup)
                 )
               end)

        Logger.flush()
        send(self(), {:pid, pid, sup})
        Supervisor.stop(sup)
      end)

    assert_received {:pid, pid, sup}
    assert [line] = killed_lines(log), log

    assert line =~
             "process #{inspect(pid)} (child Agent of #{inspect(sup)} Supervisor.Default) was killed"
  end

  test "a supervised GenServer that crashes is logged once: by itself, not again as killed" do
    log =
      capture_log(fn ->
        {:ok, sup} =
          Supervisor.start_link([%{id: :server, start: {GenServer, :start_link, [Server, %{}]}}],
            strategy: :one_for_one
          )

        [{:server, pid, _, _}] = Supervisor.which_children(sup)
        ref = Process.monitor(pid)
        catch_exit(GenServer.call(pid, :boom))
        assert_receive {:DOWN, ^ref, :process, ^pid, _}
        Logger.flush()
        Supervisor.stop(sup)
      end)

    assert [_line] = crash_lines(log), log
    assert killed_lines(log) == [], log
  end

  test "a temporary child killed (an HTTP connection shed on purpose) is not logged" do
    log =
      capture_log(fn ->
        {:ok, sup} = Task.Supervisor.start_link()
        {:ok, pid} = Task.Supervisor.start_child(sup, fn -> Process.sleep(:infinity) end)
        ref = Process.monitor(pid)
        Process.exit(pid, :kill)
        assert_receive {:DOWN, ^ref, :process, ^pid, :killed}
        Logger.flush()
        Supervisor.stop(sup)
      end)

    assert killed_lines(log) == [], log
  end
end
