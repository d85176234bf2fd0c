defmodule Mix.Tasks.Vws.Serve do
  @shortdoc "Starts a VWS workstation and waits for a workstation controller"
  @moduledoc """
  Starts one workstation (VWS_CONTROL, the mailboxes, the partitions and SUN_COMM) and waits for a
  workstation controller.

      mix vws.serve                       # WC on tcp://127.0.0.1:7070
      mix vws.serve --wc-port 7071 --bind 0.0.0.0
      mix vws.serve --wc tty:/dev/ttyUSB0?baud=9600
      iex -S mix vws.serve                # the same, with a shell to inspect it live
      mix vws.serve --http-port 8080      # the dashboard and MTConnect agent on another port

  Options:

    * `--wc-port N` — TCP port for the WC (default 7070)
    * `--bind ADDR` — address to listen on (default 127.0.0.1)
    * `--wc ENDPOINT` — any endpoint instead (`tcp://host:port`, `tty:/dev/…?baud=…`, `loopback:name`)
    * `--id ID` — the workstation id (default `VWS`)
    * `--bcc sum|xor` — the WC link's block check (default sum)
    * `--http-port N` — the dashboard and MTConnect agent (`Vws.Web`) on port N (default 4000;
      0 picks a free port)
    * `--http-bind ADDR` — the address they listen on (default 127.0.0.1)
    * `--http-token TOKEN` — enables the dashboard's control actions for requests carrying this
      token (default: `$VWS_HTTP_TOKEN`, else none: read-only)
  """
  use Mix.Task

  @switches [
    wc_port: :integer,
    bind: :string,
    wc: :string,
    id: :string,
    bcc: :string,
    http_port: :integer,
    http_bind: :string,
    http_token: :string
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

    {:ok, _} = Vws.Workstation.start(id: id, wc: wc, sun_comm: [bcc: bcc])
    listening = wait_listening(id, 50)
    Mix.shell().info("VWS workstation #{id}: SUN_COMM waits for the WC on #{listening || wc}")
    Mix.shell().info("Dashboard and MTConnect agent: #{start_web(opts)}")
    Mix.shell().info("Inspect it: Vws.Inspect.overview(#{inspect(id)})   Stop: Ctrl-C twice")

    unless iex_running?(), do: Process.sleep(:infinity)
  end

  defp wait_listening(_id, 0), do: nil

  defp wait_listening(id, n) do
    case Vws.SunComm.listening(id) do
      nil -> Process.sleep(20) && wait_listening(id, n - 1)
      endpoint -> endpoint
    end
  end

  defp iex_running?, do: Code.ensure_loaded?(IEx) and IEx.started?()

  defp start_web(opts) do
    case Vws.Web.start_from_cli(opts) do
      {:ok, url} -> url
      {:error, message} -> Mix.raise(message)
    end
  end
end
