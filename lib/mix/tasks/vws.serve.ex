defmodule Mix.Tasks.Vws.Serve do
  @shortdoc "Starts a VWS workstation and waits for a workstation controller"
  @moduledoc """
  Starts one workstation (VWS_CONTROL, the mailboxes, the partitions and SUN_COMM) and waits for a
  workstation controller.

      mix vws.serve                       # WC on tcp://127.0.0.1:7070
      mix vws.serve --wc-port 7071 --bind 0.0.0.0
      mix vws.serve --wc tty:/dev/ttyUSB0?baud=9600
      iex -S mix vws.serve                # the same, with a shell to inspect it live

  Options:

    * `--wc-port N` — TCP port for the WC (default 7070)
    * `--bind ADDR` — address to listen on (default 127.0.0.1)
    * `--wc ENDPOINT` — any endpoint instead (`tcp://host:port`, `tty:/dev/…?baud=…`, `loopback:name`)
    * `--id ID` — the workstation id (default `VWS`)
    * `--bcc sum|xor` — the WC link's block check (default sum)
    * `--robot ENDPOINT` — the VAL II's supervisory port (`tty:/dev/ttyS1?baud=9600`, a terminal
      server's `tcp://host:port`); without it a simulated VAL II (`Vws.Sim.VAL2`) is started on a
      free local port and ROBOT is connected to it
    * `--robot-time-scale F` — the simulated robot's motion time factor (default 1.0)
  """
  use Mix.Task

  @switches [
    wc_port: :integer,
    bind: :string,
    wc: :string,
    id: :string,
    bcc: :string,
    robot: :string,
    robot_time_scale: :float
  ]

  @impl true
  def run(args) do
    {opts, _rest, invalid} = OptionParser.parse(args, strict: @switches)
    if invalid != [], do: Mix.raise("unknown options: #{inspect(invalid)}")

    Mix.Task.run("app.start")

    wc = opts[:wc] || "tcp://#{opts[:bind] || "127.0.0.1"}:#{opts[:wc_port] || 7070}"
    id = opts[:id] || "VWS"

    bcc =
      case opts[:bcc] do
        nil -> :sum
        "sum" -> :sum
        "xor" -> :xor
        other -> Mix.raise("--bcc must be sum or xor, not #{other}")
      end

    robot = robot(opts)

    {:ok, _} =
      Vws.Workstation.start(id: id, wc: wc, sun_comm: [bcc: bcc], devices: [robot: robot])

    listening = wait_listening(id, 50)
    Mix.shell().info("VWS workstation #{id}: SUN_COMM waits for the WC on #{listening || wc}")
    Mix.shell().info("Inspect it: Vws.Mailbox.print(#{inspect(id)})   Stop: Ctrl-C twice")

    unless iex_running?(), do: Process.sleep(:infinity)
  end

  # the real VAL II, or a simulated one started here (outside the workstation: it is equipment)
  defp robot(opts) do
    case opts[:robot] do
      nil ->
        {:ok, sim} = Vws.Sim.VAL2.start_link(time_scale: opts[:robot_time_scale] || 1.0)
        Process.unlink(sim)
        endpoint = Vws.Sim.VAL2.endpoint(sim)
        Mix.shell().info("Simulated VAL II robot controller on #{endpoint}")
        endpoint

      endpoint ->
        Mix.shell().info("ROBOT connects to the VAL II at #{endpoint}")
        endpoint
    end
  end

  defp wait_listening(_id, 0), do: nil

  defp wait_listening(id, n) do
    case Vws.SunComm.listening(id) do
      nil -> Process.sleep(20) && wait_listening(id, n - 1)
      endpoint -> endpoint
    end
  end

  defp iex_running?, do: Code.ensure_loaded?(IEx) and IEx.started?()
end
