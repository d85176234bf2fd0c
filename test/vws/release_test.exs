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

  defp start_release(root, id) do
    assert {_, 0} = bin(root, id, ["daemon"])
    assert eventually(fn -> match?({_, 0}, bin(root, id, ["pid"])) end, 30_000)
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

    cookie = Path.join(root, "data/cookie")
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
    end
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
