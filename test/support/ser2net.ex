defmodule Vws.Test.Ser2net do
  @moduledoc """
  ser2net (the Debian package: an implementation of RFC 2217 we did not write) in front of one
  side of a pty pair, for tests: an RFC 2217 accepter on a loopback port, started from a config
  file the test writes, stopped (and its files removed) when the test exits. If ser2net is not
  installed or does not start, the test fails and says so — it is never skipped.
  """

  import ExUnit.Callbacks, only: [on_exit: 1]
  import ExUnit.Assertions, only: [flunk: 1]

  @doc "Starts ser2net serving `tty` (a path) as `rfc2217://127.0.0.1:PORT`; returns `%{port, config}`."
  def start!(tty, dir) do
    ser2net =
      System.find_executable("ser2net") || System.find_executable("/usr/sbin/ser2net") ||
        flunk("ser2net is not installed: apt-get install -y ser2net (.ci/run installs it)")

    port = Vws.Test.Acceptance.free_port()
    config = Path.join(dir, "ser2net-#{port}.yaml")

    File.write!(config, """
    connection: &vws
      accepter: telnet(rfc2217),tcp,127.0.0.1,#{port}
      connector: serialdev,#{tty},9600n81,local
      options:
        kickolduser: true
    """)

    proc =
      Port.open({:spawn_executable, ser2net}, [
        :binary,
        :exit_status,
        :stderr_to_stdout,
        args: ["-n", "-d", "-c", config, "-P", Path.join(dir, "ser2net-#{port}.pid")]
      ])

    {:os_pid, os_pid} = Port.info(proc, :os_pid)

    on_exit(fn ->
      System.cmd("kill", [Integer.to_string(os_pid)], stderr_to_stdout: true)

      Vws.TransportHelpers.wait_until(fn ->
        not Vws.Links.Transport.Serial.os_alive?(os_pid)
      end)
    end)

    await_listening(proc, port, System.monotonic_time(:millisecond) + 10_000, "")
    %{port: port, config: config, os_pid: os_pid}
  end

  defp await_listening(proc, port, deadline, log) do
    receive do
      {^proc, {:data, more}} -> await_listening(proc, port, deadline, log <> more)
      {^proc, {:exit_status, status}} -> flunk("ser2net exited with status #{status}: #{log}")
    after
      0 ->
        case :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false], 200) do
          {:ok, socket} ->
            :gen_tcp.close(socket)

          {:error, _} ->
            if System.monotonic_time(:millisecond) > deadline,
              do: flunk("ser2net never listened on port #{port}: #{log}")

            Process.sleep(50)
            await_listening(proc, port, deadline, log)
        end
    end
  end
end
