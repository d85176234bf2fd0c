defmodule Vws.ReleaseTest do
  # The release as an operator runs it (issue 16, issue 14 item 5): built with `mix release` into
  # a temporary directory and started with `bin/vws daemon` — real OS processes. Its Erlang
  # distribution (and everything else it listens on) is on loopback, its cookie is made on first
  # start with mode 0400 and is not in the build output, a second release on the host starts
  # under its own VWS_ID (or is refused with a message when the name is taken), and
  # `bin/vws rpc` / `bin/vws remote` still reach it.
  use ExUnit.Case, async: true

  import Bitwise
  import Vws.Test.Eventually

  @moduletag :acceptance
  @moduletag timeout: 300_000

  # The release is built once per run and shared with the other release test, which keeps its
  # state elsewhere; this module's state (data directory with its cookie, RELEASE_TMP) lives in
  # the release's own temporary directory, removed after the suite.
  setup_all do
    %{root: Vws.Test.Acceptance.release()}
  end

  defp env(root, id, extra \\ []) do
    [
      {"VWS_ID", id},
      {"VWS_HTTP_PORT", "0"},
      {"VWS_WC", "tcp://127.0.0.1:0"},
      {"VWS_DATA_DIR", Path.join(root, "data")},
      {"RELEASE_TMP", Path.join(root, "tmp-#{id}")},
      {"RELEASE_COOKIE", nil},
      {"RELEASE_NODE", nil}
    ] ++ extra
  end

  defp bin(root, id, args, extra \\ []) do
    System.cmd(Path.join(root, "bin/vws"), args, env: env(root, id, extra), stderr_to_stdout: true)
  end

  # The daemon answers `pid` once its node is up. Up to 60 s (a CI run at full load once took
  # more than 30); failing, it says what the last `pid` printed and what the node logged.
  defp await_daemon(root, id) do
    last = :ets.new(:last_pid_answer, [:public])

    up? =
      eventually(
        fn ->
          {out, status} = bin(root, id, ["pid"])
          :ets.insert(last, {:answer, status, out})
          status == 0
        end,
        60_000
      )

    unless up? do
      [{:answer, status, out}] = :ets.lookup(last, :answer)
      logs = Path.wildcard(Path.join([root, "tmp-#{id}", "log", "*"]))

      tail =
        Enum.map_join(logs, "\n", &"#{&1}:\n#{&1 |> File.read!() |> String.slice(-3_000..-1)}")

      flunk(
        "the release #{id} did not answer `pid` in 60 s (last: exit #{status}, #{inspect(out)})\n#{tail}"
      )
    end
  end

  defp start_release(root, id) do
    assert {_, 0} = bin(root, id, ["daemon"])
    await_daemon(root, id)
    {pid, 0} = bin(root, id, ["pid"])
    os_pid = String.trim(pid)
    on_exit(fn -> stop_release(root, id, os_pid) end)
    os_pid
  end

  # `bin/vws stop` only asks: wait for the OS process to end (killed if it has not in 30 s)
  defp stop_release(root, id, os_pid) do
    bin(root, id, ["stop"])
    alive? = fn -> match?({_, 0}, System.cmd("kill", ["-0", os_pid], stderr_to_stdout: true)) end

    unless eventually(fn -> not alive?.() end, 30_000),
      do: System.cmd("kill", ["-9", os_pid], stderr_to_stdout: true)
  end

  # every process on the host: [{"1234", "argv joined by spaces"}]
  defp cmdlines do
    for pid <- File.ls!("/proc"),
        pid =~ ~r/^\d+$/,
        {:ok, bytes} <- [File.read("/proc/#{pid}/cmdline")],
        bytes != "",
        do: {pid, String.replace(bytes, <<0>>, " ")}
  end

  # the processes whose command line holds one of `secrets`
  defp no_secret(cmdlines, secrets) do
    for {pid, line} <- cmdlines,
        secret <- List.wrap(secrets),
        String.contains?(line, secret),
        do: {pid, line}
  end

  defp http_status(port, token) do
    {:ok, _} = Application.ensure_all_started(:inets)
    headers = if token, do: [{~c"x-vws-token", String.to_charlist(token)}], else: []

    case :httpc.request(:get, {~c"http://127.0.0.1:#{port}/current", headers}, [timeout: 10_000],
           body_format: :binary
         ) do
      {:ok, {{_, status, _}, _, _}} -> status
      {:error, _} -> :no_answer
    end
  end

  # every listening socket of an OS process: ["127.0.0.1:4000", …]
  defp listening(os_pid) do
    {out, 0} = System.cmd("ss", ["-ltnpH"])

    for line <- String.split(out, "\n", trim: true),
        String.contains?(line, "pid=#{os_pid},") do
      line |> String.split(~r/\s+/, trim: true) |> Enum.at(3)
    end
  end

  test "distribution on loopback, a per-installation cookie 0400 not in the build, rpc and remote work",
       %{root: root} do
    refute File.exists?(Path.join(root, "releases/COOKIE"))
    id = "relA#{System.unique_integer([:positive])}"
    node = "vws_#{String.downcase(id)}@127.0.0.1"
    os_pid = start_release(root, id)

    cookie = Path.join(root, "data/.erlang.cookie")
    assert {:ok, %File.Stat{mode: mode}} = File.stat(cookie)
    assert (mode &&& 0o777) == 0o400
    assert byte_size(File.read!(cookie)) == 64

    # the node answers rpc under its VWS_ID-derived name; the dist port is among its listeners
    assert {out, 0} = bin(root, id, ["rpc", "IO.puts(node())"])
    assert String.trim(out) == node

    assert {port, 0} =
             bin(root, id, [
               "rpc",
               "{:ok, names} = :erl_epmd.names(); " <>
                 "IO.puts(List.keyfind(names, 'vws_#{String.downcase(id)}', 0) |> elem(1))"
             ])

    # everything the node listens on (distribution, HTTP, the WC port) is loopback
    assert eventually(fn -> length(listening(os_pid)) >= 3 end, 10_000)
    addresses = listening(os_pid)
    assert "127.0.0.1:#{String.trim(port)}" in addresses

    assert Enum.all?(addresses, &(String.starts_with?(&1, "127.0.0.1:") or &1 =~ ~r/^\[::1\]:/)),
           "listening beyond loopback: #{inspect(addresses)}"

    # a cookie others can read is refused
    File.chmod!(cookie, 0o644)
    assert {out, 1} = bin(root, id, ["rpc", "IO.puts(1)"])
    assert out =~ "readable by others"
    File.chmod!(cookie, 0o400)

    # bin/vws remote: a shell on the node (under tmux: remote needs a terminal)
    if System.find_executable("tmux") do
      session = "vws-remote-#{System.unique_integer([:positive])}"
      exports = Enum.map_join(env(root, id), " ", fn {k, v} -> "#{k}=#{v || ""}" end)

      {_, 0} =
        System.cmd("tmux", [
          "new-session",
          "-d",
          "-s",
          session,
          "-x",
          "200",
          "-y",
          "40",
          "env -u RELEASE_COOKIE -u RELEASE_NODE #{exports} #{root}/bin/vws remote"
        ])

      on_exit(fn -> System.cmd("tmux", ["kill-session", "-t", session]) end)
      pane = fn -> elem(System.cmd("tmux", ["capture-pane", "-p", "-t", session]), 0) end
      assert eventually(fn -> pane.() =~ "iex(#{node})" end, 20_000), pane.()

      System.cmd("tmux", [
        "send-keys",
        "-t",
        session,
        ~s|IO.puts("ON " <> to_string(node()))|,
        "Enter"
      ])

      assert eventually(fn -> pane.() =~ "ON #{node}" end, 10_000), pane.()

      # the remote shell's own VM holds no cookie on its command line either
      cmdlines = cmdlines()
      assert Enum.any?(cmdlines, fn {_, line} -> line =~ "rem-" and line =~ root end), pane.()
      assert no_secret(cmdlines, File.read!(cookie)) == []
    end

    # the cookie is never taken from the environment: that would put it on the command line
    assert {out, 1} = bin(root, id, ["rpc", "IO.puts(1)"], [{"RELEASE_COOKIE", "abc"}])
    assert out =~ "RELEASE_COOKIE is not used"
    assert out =~ ".erlang.cookie (mode 0400)"
  end

  # Issue 30 item 5: /proc/<pid>/cmdline is readable by every local user, who would connect with
  # the cookie and run code as the service's user, or use a token. Every process on the host is
  # read (NUL-separated argv → spaces) while the release runs, while an rpc runs (its own VM
  # included, read from inside the node) and while a remote shell is open (the first test).
  test "no secret on a command line: the cookie and the tokens are in no process's argv; rpc works",
       %{root: root} do
    id = "relS#{System.unique_integer([:positive])}"
    secrets = Path.join(root, "secrets-#{id}")
    File.mkdir_p!(secrets)
    control = "control-#{Base.encode16(:crypto.strong_rand_bytes(16))}"
    read = "read-#{Base.encode16(:crypto.strong_rand_bytes(16))}"
    File.write!(Path.join(secrets, "control"), control <> "\n")
    File.write!(Path.join(secrets, "read"), read <> "\n")
    File.chmod!(Path.join(secrets, "control"), 0o600)
    File.chmod!(Path.join(secrets, "read"), 0o600)
    http = Vws.Test.Acceptance.free_port()

    extra = [
      {"VWS_HTTP_PORT", "#{http}"},
      {"VWS_HTTP_TOKEN_FILE", Path.join(secrets, "control")},
      {"VWS_HTTP_READ_TOKEN_FILE", Path.join(secrets, "read")}
    ]

    {_, 0} = System.cmd(Path.join(root, "bin/vws"), ["daemon"], env: env(root, id, extra))
    await_daemon(root, id)
    {os_pid, 0} = bin(root, id, ["pid"])
    os_pid = String.trim(os_pid)
    on_exit(fn -> stop_release(root, id, os_pid) end)

    cookie = File.read!(Path.join(root, "data/.erlang.cookie"))
    assert cookie =~ ~r/^[0-9a-f]{64}$/

    # the tokens were read from their files: reads need the read token, and it works
    assert eventually(fn -> http_status(http, nil) == 401 end, 20_000)
    assert http_status(http, read) == 200
    assert http_status(http, control) == 200

    # the release's processes: the node (beam.smp), run_erl holding its command, EPMD
    cmdlines = cmdlines()
    {_, node_line} = List.keyfind(cmdlines, os_pid, 0)
    assert node_line =~ "beam.smp" and node_line =~ root and node_line =~ "-name vws_"
    assert Enum.any?(cmdlines, fn {_, line} -> line =~ "run_erl" and line =~ root end)
    assert Enum.any?(cmdlines, fn {_, line} -> line =~ ~r{(^|/)epmd } end)
    assert no_secret(cmdlines, [cookie, control, read]) == []

    # nor in the node's environment (readable by its user only, but the cookie has no need there)
    environ = File.read!("/proc/#{os_pid}/environ")
    refute environ =~ cookie
    refute environ =~ control

    # bin/vws rpc still works, and its own VM (rpc-…) is among the processes it sees, clean
    read_all =
      ~S|for p <- File.ls!("/proc"), p =~ ~r/^\d+$/, | <>
        ~S|{:ok, c} <- [File.read("/proc/#{p}/cmdline")], c != "", | <>
        ~S|do: IO.puts(p <> " " <> String.replace(c, [<<0>>, "\n", "\r"], " "))|

    assert {out, 0} = bin(root, id, ["rpc", read_all])

    # a command line may hold newlines (a shell's -c script): the rpc turns them into spaces, and
    # a line that is not "<pid> <command line>" (output of the rpc itself) is left out
    seen =
      for line <- String.split(out, "\n", trim: true),
          [pid, command] <- [String.split(line, " ", parts: 2)],
          pid =~ ~r/^\d+$/,
          do: {pid, command}

    assert Enum.any?(seen, fn {_, line} -> line =~ "rpc-" and line =~ "--rpc-eval" end), out
    assert List.keymember?(seen, os_pid, 0)
    assert no_secret(seen, [cookie, control, read]) == []
  end

  test "a second release on the host starts under its own VWS_ID; the same name is refused with a message",
       %{root: root} do
    id = "relB#{System.unique_integer([:positive])}"
    _ = start_release(root, id)

    assert {out, 1} = bin(root, id, ["daemon"])
    assert out =~ "a node named vws_#{String.downcase(id)} is already running on this host"

    other = id <> "x"
    _ = start_release(root, other)
    assert {out, 0} = bin(root, other, ["rpc", "IO.puts(node())"])
    assert String.trim(out) == "vws_#{String.downcase(other)}@127.0.0.1"
    assert {out, 0} = bin(root, id, ["rpc", "IO.puts(node())"])
    assert String.trim(out) == "vws_#{String.downcase(id)}@127.0.0.1"
  end
end
