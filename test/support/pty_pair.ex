defmodule Vws.Test.PtyPair do
  @moduledoc """
  A null-modem cable for tests: `socat` makes two ptys, `a` and `b`, and relays between them, so
  each end can be opened as a real serial line (`"tty:" <> a`).
  """

  import ExUnit.Callbacks, only: [on_exit: 1]
  import ExUnit.Assertions, only: [flunk: 1]

  @doc """
  Starts the pair; it is killed and its files removed when the test exits. `dir:` puts the two
  links in a directory of the caller's (a cable plugged in again where it was).
  """
  def start!(opts \\ []) do
    dir =
      Keyword.get_lazy(opts, :dir, fn ->
        Path.join(System.tmp_dir!(), "vws-tty-#{System.unique_integer([:positive])}")
      end)

    File.mkdir_p!(dir)
    a = Path.join(dir, "a")
    b = Path.join(dir, "b")

    # -d -d makes socat say when both ptys exist and it relays between them.
    cable =
      Port.open({:spawn_executable, System.find_executable("socat")}, [
        :binary,
        :exit_status,
        :stderr_to_stdout,
        args: ["-d", "-d", "pty,raw,echo=0,link=#{a}", "pty,raw,echo=0,link=#{b}"]
      ])

    {:os_pid, cable_pid} = Port.info(cable, :os_pid)
    await_log(cable, "starting data transfer loop", "")

    on_exit(fn ->
      System.cmd("kill", [Integer.to_string(cable_pid)], stderr_to_stdout: true)

      Vws.TransportHelpers.wait_until(fn ->
        not Vws.Links.Transport.Serial.os_alive?(cable_pid)
      end)

      File.rm_rf!(dir)
    end)

    %{a: a, b: b, dir: dir, cable: cable, cable_pid: cable_pid}
  end

  defp await_log(port, line, seen) do
    if seen =~ line do
      :ok
    else
      receive do
        {^port, {:data, log}} -> await_log(port, line, seen <> log)
        {^port, {:exit_status, status}} -> flunk("socat exited with #{status}: #{seen}")
      after
        5000 -> flunk("socat never said #{inspect(line)}: #{seen}")
      end
    end
  end
end
