defmodule Vws.Test.Acceptance do
  @moduledoc ~S"""
  The harness of the end-to-end acceptance tests: real OS processes started the way the README
  says (`mix vws.serve`, `iex -S mix vws.serve` under tmux, `mix vws.demo`, the release), driven
  through real TCP and HTTP, and stopped with real signals.

  ## OS processes

      :ok = Acceptance.prebuild("dev")                 # once per run: `MIX_ENV=dev mix compile`
      wc = Acceptance.free_port()
      proc = Acceptance.start(["mix", "vws.serve", "--wc-port", "#{wc}"], env: [{"MIX_ENV", "dev"}])
      [_, port] = Acceptance.await(proc, ~r/waits for the WC on tcp:\/\/127.0.0.1:(\d+)/)
      Acceptance.signal(proc, "TERM")
      0 = Acceptance.await_exit(proc)
      Acceptance.output(proc)                          # stdout and stderr, as the user saw them

  Every process started here gets a data directory of its own (`VWS_DATA_DIR`, a fresh
  temporary directory) unless `:env` names one: the journal is on by default and holds one OS
  process per directory, so two tests (or a test and a developer's own `mix vws.serve`) never
  share one, and no run restores another's commands.

  `start/2` runs the command in a session (and process group) of its own, through a small `sh`
  wrapper: the command is `exec`ed (so `signal/2` reaches the program itself, e.g. the BEAM
  behind `mix`), and a watcher in the group kills the whole group as soon as the harness's port
  closes — when `stop/1` is called, when the owner (the process that called `start/2`) exits, or
  when the test VM dies. Nothing started here outlives the test run. The first argument is
  looked up in `PATH`; `:env` (added to the test VM's environment — give `MIX_ENV` explicitly,
  the test VM's is `test`) and `:cd` (default: the project root) are the options.

  Spawning `mix` from inside `mix test`: give the child another `MIX_ENV` (usually `dev`) than
  the test VM's build, and compile that environment once with `prebuild/1` before the first
  start, so that concurrent children never compile (Elixir 1.14 has no build lock).

  ## A shell under tmux

      t = Acceptance.tmux_start("iex -S mix vws.serve --wc-port 7171", env: [{"MIX_ENV", "dev"}])
      Acceptance.tmux_await(t, ~r/iex\(1\)>/)
      Acceptance.tmux_send(t, ~s|Vws.Ops.Inspect.overview("VWS")|)   # typed, then Enter
      Acceptance.tmux_capture(t)                                 # the pane's text (with history)
      Acceptance.tmux_keys(t, ["C-\\"])                          # keys by tmux name (Ctrl-\)
      0 = Acceptance.tmux_await_exit(t)                          # the pane stays after the exit
      Acceptance.tmux_stop(t)

  Each tmux session runs on a tmux server of its own (`tmux -L <socket>`), killed by
  `tmux_stop/1`.

  ## Talking to what runs

    * `free_port/0` — a TCP port free on 127.0.0.1 right now
    * `wc_request/3` — one WC string over real TCP (framed with its BCC here), its reply line
    * `wc_frame/1` — `"*0001*S0001ROBOT_CMD*"` → `"*0001*S0001ROBOT_CMD*012"` (sum BCC)
    * `http_get/2` — `{status, body}` of `GET http://127.0.0.1:port/path`

  Every wait has a deadline (monotonic time) and fails the test with the output so far.
  """

  import ExUnit.Assertions
  import Vws.Codecs.WC.Command, only: [pad4: 1]

  @root Path.expand("../..", __DIR__)

  @doc "The project's root directory (where mix.exs is)."
  def root, do: @root

  ## Building

  @doc """
  Compiles the project in `mix_env` (`"dev"`, `"prod"`) once per test run, outside the test
  VM's build; concurrent callers wait for the first one.
  """
  def prebuild(mix_env) do
    once({:prebuilt, mix_env}, fn ->
      {out, status} =
        System.cmd(mix(), ["compile"],
          env: [{"MIX_ENV", mix_env}],
          cd: @root,
          stderr_to_stdout: true
        )

      if status != 0, do: flunk("MIX_ENV=#{mix_env} mix compile failed:\n#{out}")
      true
    end)

    :ok
  end

  @doc """
  The release, built once per test run with `MIX_ENV=prod mix release` into a temporary directory
  (removed after the suite) and shared by every test that starts it; concurrent callers wait for
  the first one. Tests keep their own state out of it: each gives its release its own
  `VWS_DATA_DIR`, `RELEASE_TMP` and `VWS_ID`.
  """
  def release do
    once(:release, fn ->
      path = Path.join(System.tmp_dir!(), "vws-release-#{System.unique_integer([:positive])}")

      {out, status} =
        System.cmd(mix(), ["release", "--path", path, "--overwrite", "--quiet"],
          env: [{"MIX_ENV", "prod"}],
          cd: @root,
          stderr_to_stdout: true
        )

      if status != 0, do: flunk("MIX_ENV=prod mix release failed:\n#{out}")
      ExUnit.after_suite(fn _ -> File.rm_rf(path) end)
      path
    end)
  end

  # `fun`'s value, made by the first caller in this test run; concurrent callers wait for it.
  defp once(name, fun) do
    key = {__MODULE__, name}

    :global.trans({key, self()}, fn ->
      case :persistent_term.get(key, nil) do
        nil ->
          value = fun.()
          :persistent_term.put(key, value)
          value

        value ->
          value
      end
    end)
  end

  defp mix, do: System.find_executable("mix") || flunk("mix is not in PATH")

  @doc """
  Called once before the suite: when no `epmd` answers on this host now, one that a test starts
  (a distributed test node — `Vws.Test.CellPeers` —, a release with distribution on) is
  stopped after the suite, so that the suite leaves no daemon running. An `epmd` that was there
  before is left alone, and `epmd -kill` refuses while any node is still registered with it.
  """
  def stop_epmd_after_suite do
    if match?({:error, _}, :erl_epmd.names(~c"127.0.0.1")) do
      ExUnit.after_suite(fn _ ->
        _ = :net_kernel.stop()

        with {:ok, _} <- :erl_epmd.names(~c"127.0.0.1"),
             epmd when is_binary(epmd) <- epmd_executable() do
          System.cmd(epmd, ["-kill"], stderr_to_stdout: true)
        end
      end)
    end

    :ok
  end

  defp epmd_executable do
    System.find_executable("epmd") ||
      Path.join([:code.root_dir(), "erts-#{:erlang.system_info(:version)}", "bin", "epmd"])
  end

  ## OS processes

  # The wrapper: a watcher in the background kills the process group when its stdin (the
  # port) closes; the command replaces the shell, keeping the shell's pid (the group's id).
  @wrapper ~S"""
  exec 3<&0
  ( read -r _ <&3; kill -s KILL -- -$$ ) >/dev/null 2>&1 </dev/null &
  echo "@@acceptance-pid $$"
  exec "$@" </dev/null 3<&-
  """

  @doc "Starts `argv` as an OS process in its own process group. Options: `:env`, `:cd`."
  def start([command | args], opts \\ []) do
    executable =
      if String.contains?(command, "/"),
        do: Path.expand(command, Keyword.get(opts, :cd, @root)),
        else: System.find_executable(command) || flunk("#{command} is not in PATH")

    owner = self()
    {:ok, pid} = GenServer.start(__MODULE__.Proc, {owner, executable, args, opts})
    pid
  end

  @doc """
  `mix vws.serve ARGS` started as a user starts it (`start/2`'s `opts`: `env:` and so on),
  stopped when the test ends, and returned once SUN_COMM waits for the WC (`timeout` ms).
  """
  def serve(args, opts, timeout \\ 120_000) do
    proc = start(["mix", "vws.serve" | args], opts)
    ExUnit.Callbacks.on_exit(fn -> stop(proc) end)
    await(proc, ~r/SUN_COMM waits for the WC/, timeout)
    proc
  end

  @doc "Everything the process wrote so far (stdout and stderr together)."
  def output(proc), do: GenServer.call(proc, :output)

  @doc "The OS pid of the process (the program `exec`ed by the wrapper)."
  def os_pid(proc), do: GenServer.call(proc, :os_pid)

  @doc """
  Waits until the output matches `regex` and returns its captures (`Regex.run/2`); fails the
  test with the output if `timeout` ms pass first or the process exits without matching.
  """
  def await(proc, regex, timeout \\ 60_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    await_loop(proc, regex, deadline)
  end

  defp await_loop(proc, regex, deadline) do
    %{output: out, status: status} = GenServer.call(proc, :state)

    cond do
      match = Regex.run(regex, out) ->
        match

      status != nil ->
        flunk("the process exited (status #{status}) before #{inspect(regex)}; output:\n#{out}")

      System.monotonic_time(:millisecond) > deadline ->
        flunk("no #{inspect(regex)} in time; output so far:\n#{out}")

      true ->
        Process.sleep(50)
        await_loop(proc, regex, deadline)
    end
  end

  @doc "Sends signal `sig` (`\"TERM\"`, `\"INT\"`, `\"QUIT\"`, …) to the process itself."
  def signal(proc, sig) do
    {_, 0} = System.cmd("kill", ["-s", sig, "--", Integer.to_string(os_pid(proc))])
    :ok
  end

  @doc "Waits for the process to exit and returns its exit status; fails the test after `timeout` ms."
  def await_exit(proc, timeout \\ 30_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    await_exit_loop(proc, deadline)
  end

  defp await_exit_loop(proc, deadline) do
    %{output: out, status: status} = GenServer.call(proc, :state)

    cond do
      status != nil ->
        status

      System.monotonic_time(:millisecond) > deadline ->
        flunk("the process did not exit in time; output so far:\n#{out}")

      true ->
        Process.sleep(50)
        await_exit_loop(proc, deadline)
    end
  end

  @doc "Runs a command to its end (`start/2`'s `opts`): `{exit status, output}`."
  def run(command, opts \\ [], timeout \\ 120_000) do
    proc = start(command, opts)
    status = await_exit(proc, timeout)
    {status, output(proc)}
  end

  @doc "Kills the process and everything in its group (SIGKILL); returns the output. Idempotent."
  def stop(proc) do
    if Process.alive?(proc) do
      try do
        GenServer.call(proc, :stop, 10_000)
      catch
        :exit, _ -> ""
      end
    else
      ""
    end
  end

  ## tmux

  @doc """
  Starts `command` (a shell command line, run in the project root) in a new detached tmux
  session on a tmux server of its own, 200 columns wide. Options: `:env`.
  """
  def tmux_start(command, opts \\ []) do
    socket = "vws-acceptance-#{System.unique_integer([:positive])}"

    env =
      for {k, v} <- with_data_dir(Keyword.get(opts, :env, [])),
          do: "#{k}=#{shell_quote(v)} "

    line = "cd #{shell_quote(@root)} && exec env #{Enum.join(env)}#{command}"

    {out, status} =
      System.cmd(
        "tmux",
        ["-L", socket, "new-session", "-d", "-s", "main", "-x", "200", "-y", "50", line],
        stderr_to_stdout: true
      )

    if status != 0, do: flunk("tmux new-session failed: #{out}")
    {_, 0} = tmux(socket, ["set-option", "-t", "main", "history-limit", "20000"])
    # the pane stays when its program exits, for tmux_capture/1 and tmux_await_exit/2
    {_, 0} = tmux(socket, ["set-option", "-t", "main", "remain-on-exit", "on"])
    %{socket: socket}
  end

  @doc "Types `text` into the session's pane, then Enter."
  def tmux_send(%{socket: socket}, text) do
    {_, 0} = tmux(socket, ["send-keys", "-t", "main", "-l", text])
    {_, 0} = tmux(socket, ["send-keys", "-t", "main", "Enter"])
    :ok
  end

  @doc "Sends keys by their tmux names (`\"C-c\"`, `\"C-\\\\\"`, `\"Enter\"`)."
  def tmux_keys(%{socket: socket}, keys) do
    {_, 0} = tmux(socket, ["send-keys", "-t", "main" | keys])
    :ok
  end

  @doc "The pane's text, its scroll-back included."
  def tmux_capture(%{socket: socket}) do
    case tmux(socket, ["capture-pane", "-p", "-J", "-S", "-20000", "-t", "main"]) do
      {out, 0} -> out
      {out, _} -> "(no pane: #{out})"
    end
  end

  @doc "Waits until the pane's text matches `regex`; returns the captures or fails with the pane."
  def tmux_await(t, regex, timeout \\ 60_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    tmux_await_loop(t, regex, deadline)
  end

  defp tmux_await_loop(t, regex, deadline) do
    text = tmux_capture(t)

    cond do
      match = Regex.run(regex, text) ->
        match

      System.monotonic_time(:millisecond) > deadline ->
        flunk("no #{inspect(regex)} in the tmux pane in time; pane:\n#{text}")

      true ->
        Process.sleep(100)
        tmux_await_loop(t, regex, deadline)
    end
  end

  @doc """
  Waits until the pane's program has exited; returns its exit status (fails after `timeout`).

  tmux does not always reap its pane's program when its server was started from the BEAM (the
  program stays a zombie, the pane never "dead"), so the exit is also read from the kernel:
  `/proc/PID/stat`'s exit code of the zombie.
  """
  def tmux_await_exit(%{socket: socket} = t, timeout \\ 30_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    pid = tmux_pid(t)

    Stream.repeatedly(fn ->
      {out, 0} =
        tmux(socket, ["list-panes", "-t", "main", "-F", "\#{pane_dead} \#{pane_dead_status}"])

      {String.split(out), zombie_status(pid)}
    end)
    |> Enum.find_value(fn
      {["1", status], _} ->
        String.to_integer(status)

      {_, status} when is_integer(status) ->
        status

      _ ->
        if System.monotonic_time(:millisecond) > deadline,
          do: flunk("the pane's program did not exit in time; pane:\n#{tmux_capture(t)}"),
          else: Process.sleep(100) && nil
    end)
  end

  # The exit status of a process that has exited but not been reaped (state Z): the last field of
  # /proc/PID/stat is its wait status (exit status << 8, or the signal: 128 + signal as a shell
  # reports it); nil while it runs.
  defp zombie_status(pid) do
    with {:ok, stat} <- File.read("/proc/#{pid}/stat"),
         [_, rest] <- String.split(stat, ") ", parts: 2),
         ["Z" | fields] <- String.split(rest) do
      wait = fields |> List.last() |> String.to_integer()

      if Bitwise.band(wait, 0x7F) == 0,
        do: Bitwise.bsr(wait, 8),
        else: 128 + Bitwise.band(wait, 0x7F)
    else
      _ -> nil
    end
  end

  @doc "The OS pid of the program in the session's pane."
  def tmux_pid(%{socket: socket}) do
    {out, 0} = tmux(socket, ["list-panes", "-t", "main", "-F", "\#{pane_pid}"])
    out |> String.trim() |> String.to_integer()
  end

  @doc "Ends the session: SIGKILL to the pane's program and its group, then the tmux server."
  def tmux_stop(%{socket: socket}) do
    socket_path =
      case tmux(socket, ["display-message", "-p", "\#{socket_path}"]) do
        {out, 0} -> String.trim(out)
        _ -> nil
      end

    case tmux(socket, ["list-panes", "-t", "main", "-F", "\#{pane_pid}"]) do
      {out, 0} ->
        pid = String.trim(out)
        System.cmd("kill", ["-s", "KILL", "--", "-" <> pid], stderr_to_stdout: true)
        System.cmd("kill", ["-s", "KILL", "--", pid], stderr_to_stdout: true)

      _ ->
        :ok
    end

    tmux(socket, ["kill-server"])
    # (a server whose pane program tmux never reaped can leave its socket behind)
    if socket_path, do: File.rm(socket_path)
    :ok
  end

  defp tmux(socket, args), do: System.cmd("tmux", ["-L", socket | args], stderr_to_stdout: true)

  defp shell_quote(value), do: "'" <> String.replace(to_string(value), "'", ~S('\'')) <> "'"

  ## Talking to it

  @doc """
  A TCP port free on 127.0.0.1 at this moment, below the kernel's ephemeral range
  (`/proc/sys/net/ipv4/ip_local_port_range`, 32768 and up by default): the OS gives ports of
  that range to every `port 0` listener and connection — the simulators of the process the
  test then starts, the other tests' — so a port picked there could be taken before the process
  binds it (`:eaddrinuse`, seen). Picked at random among 20000–32767, each port at most once
  per run.
  """
  def free_port do
    port = 20_000 + :rand.uniform(12_767) - 1
    key = {__MODULE__, :port, port}

    taken? =
      :global.trans({{__MODULE__, :ports}, self()}, fn ->
        with nil <- :persistent_term.get(key, nil),
             {:ok, socket} <- :gen_tcp.listen(port, ip: {127, 0, 0, 1}, reuseaddr: true) do
          :gen_tcp.close(socket)
          :persistent_term.put(key, true)
          false
        else
          _ -> true
        end
      end)

    if taken?, do: free_port(), else: port
  end

  @doc ~S"""
  The WC string `data` (`"*0001*S0001ROBOT_CMD*"`) with its block check (8-bit sum, three digits).

      iex> Vws.Test.Acceptance.wc_frame("*0001*S0001ROBOT_CMD*")
      "*0001*S0001ROBOT_CMD*012"
  """
  def wc_frame(data) do
    sum = data |> :binary.bin_to_list() |> Enum.sum() |> rem(256)
    data <> String.pad_leading(Integer.to_string(sum), 3, "0")
  end

  @doc """
  Polls the WC status command `status` (`"FIXTURE_CMD"`, …) over `wc_request/3`, one sequence
  number after another from `seq`, until command `number` has ended DONE or ERROR; returns that
  status line. Fails the test at `deadline` (monotonic ms).
  """
  def await_command(port, status, seq, number, deadline) do
    reply = wc_request(port, "*#{pad4(seq)}*S#{pad4(seq)}#{status}*")

    cond do
      reply =~ ~r/^\d\dS#{pad4(seq)}#{pad4(number)}(DONE|ERROR)/ ->
        reply

      System.monotonic_time(:millisecond) > deadline ->
        flunk("#{status} command #{number} did not end: #{reply}")

      true ->
        Process.sleep(100)
        await_command(port, status, seq + 1, number, deadline)
    end
  end

  @doc """
  Connects to the WC link on `127.0.0.1:port` (retrying until `timeout`), sends `data` framed
  with `wc_frame/1` and `\r\n`, and returns the first reply line (without its line end).
  """
  def wc_request(port, data, timeout \\ 10_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    socket = connect_retrying(port, deadline)

    try do
      :ok = :gen_tcp.send(socket, wc_frame(data) <> "\r\n")

      case :gen_tcp.recv(socket, 0, max(deadline - System.monotonic_time(:millisecond), 1)) do
        {:ok, line} -> String.trim_trailing(line, "\n") |> String.trim_trailing("\r")
        {:error, reason} -> flunk("no WC reply to #{data}: #{inspect(reason)}")
      end
    after
      :gen_tcp.close(socket)
    end
  end

  defp connect_retrying(port, deadline) do
    case :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, packet: :line], 1_000) do
      {:ok, socket} ->
        socket

      {:error, reason} ->
        if System.monotonic_time(:millisecond) > deadline,
          do: flunk("cannot connect to 127.0.0.1:#{port}: #{inspect(reason)}"),
          else: Process.sleep(100) && connect_retrying(port, deadline)
    end
  end

  @doc "`{status, body}` of `GET http://127.0.0.1:port<path>`."
  def http_get(port, path) do
    {:ok, _} = Application.ensure_all_started(:inets)
    url = ~c"http://127.0.0.1:#{port}#{path}"

    case :httpc.request(:get, {url, []}, [timeout: 10_000], body_format: :binary) do
      {:ok, {{_, status, _}, _headers, body}} -> {status, body}
      {:error, reason} -> flunk("GET #{url} failed: #{inspect(reason)}")
    end
  end

  defmodule Proc do
    @moduledoc false
    # Owns the port of one OS process started by Vws.Test.Acceptance.start/2.
    use GenServer

    @impl true
    def init({owner, executable, args, opts}) do
      Process.monitor(owner)

      env =
        for {k, v} <- Vws.Test.Acceptance.with_data_dir(Keyword.get(opts, :env, [])),
            do: {String.to_charlist(k), v && String.to_charlist(v)}

      port =
        Port.open({:spawn_executable, System.find_executable("setsid")}, [
          :binary,
          :exit_status,
          :stderr_to_stdout,
          :use_stdio,
          :hide,
          args: [
            "-w",
            "sh",
            "-c",
            Vws.Test.Acceptance.wrapper(),
            "vws-acceptance",
            executable | args
          ],
          env: env,
          cd: Keyword.get(opts, :cd, Vws.Test.Acceptance.root())
        ])

      {:ok, %{port: port, output: "", os_pid: nil, status: nil}}
    end

    @impl true
    def handle_info({port, {:data, data}}, %{port: port} = state) do
      output = state.output <> data

      case state.os_pid do
        nil ->
          case Regex.run(~r/\A@@acceptance-pid (\d+)\n/, output) do
            [header, pid] ->
              rest = binary_part(output, byte_size(header), byte_size(output) - byte_size(header))
              {:noreply, %{state | os_pid: String.to_integer(pid), output: rest}}

            nil ->
              {:noreply, %{state | output: output}}
          end

        _ ->
          {:noreply, %{state | output: output}}
      end
    end

    def handle_info({port, {:exit_status, status}}, %{port: port} = state),
      do: {:noreply, %{state | status: status}}

    def handle_info({:DOWN, _, :process, _owner, _}, state), do: {:stop, :normal, state}
    def handle_info(_other, state), do: {:noreply, state}

    @impl true
    def handle_call(:output, _from, state), do: {:reply, state.output, state}
    def handle_call(:state, _from, state), do: {:reply, state, state}

    def handle_call(:os_pid, from, %{os_pid: nil} = state) do
      # the wrapper prints its pid first thing; wait for it
      Process.sleep(20)
      handle_call_later(from, state)
    end

    def handle_call(:os_pid, _from, state), do: {:reply, state.os_pid, state}

    def handle_call(:stop, _from, state) do
      kill_group(state)
      {:stop, :normal, state.output, state}
    end

    defp handle_call_later(from, state) do
      receive do
        {port, {:data, _}} = msg when port == state.port ->
          {:noreply, state} = handle_info(msg, state)
          handle_call(:os_pid, from, state)
      after
        5_000 -> {:reply, nil, state}
      end
    end

    @impl true
    def terminate(_reason, state), do: kill_group(state)

    defp kill_group(%{os_pid: pid, port: port, status: status}) do
      if pid && status == nil,
        do: System.cmd("kill", ["-s", "KILL", "--", "-#{pid}"], stderr_to_stdout: true)

      # closing the port also makes the group's watcher kill whatever is left in it
      try do
        Port.close(port)
      catch
        _, _ -> :ok
      end

      :ok
    end
  end

  @doc false
  def wrapper, do: @wrapper

  defp data_root do
    once(:data_root, fn ->
      root = Path.join(System.tmp_dir!(), "vws-acceptance-data-#{System.pid()}")
      File.rm_rf!(root)
      ExUnit.after_suite(fn _ -> File.rm_rf(root) end)
      root
    end)
  end

  @doc false
  # `env` with a fresh `VWS_DATA_DIR` unless it names one (see the moduledoc).
  def with_data_dir(env) do
    if List.keymember?(env, "VWS_DATA_DIR", 0) do
      env
    else
      # always empty: unique integers start again in every test run, and a directory left by
      # an earlier run (its journal restored the mailboxes: a FIXTURE command "already DONE")
      # must not be taken over; the run's directories go with the suite
      dir = Path.join(data_root(), Integer.to_string(System.unique_integer([:positive])))
      File.rm_rf!(dir)
      File.mkdir_p!(dir)
      [{"VWS_DATA_DIR", dir} | env]
    end
  end
end
