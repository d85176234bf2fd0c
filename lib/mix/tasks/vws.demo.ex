defmodule Mix.Tasks.Vws.Demo do
  @shortdoc "Runs a machining cycle as the workstation controller against a simulated shop floor"
  @moduledoc """
  Starts a workstation with every device that can be simulated, then acts as the workstation
  controller (the Sun): runs a cycle script over the WC link and prints the dialogue — time,
  line sent, reply, meaning — and a summary. See `Vws.Ops.Demo`.

      mix vws.demo                          # the full machining cycle, then keeps running
      mix vws.demo --once                   # exit at the end: status 0 only if the cycle completed
      mix vws.demo --script priv/sims/table1.vws
      mix vws.demo --time-scale 10          # simulated equipment ten times faster
      mix vws.demo --ber 1e-4 --seed 3      # a noisy line in every link, WC link included

  Options:

    * `--once` — exit when the script ends; the exit status is 0 only if it completed
    * `--script FILE` — another cycle script (format: `Vws.Peers.WC.Script`); default
      `priv/sims/machining_cycle.vws`
    * `--time-scale N` — passed to the shop floor's simulators (default 1)
    * `--wc-port N` — the TCP port SUN_COMM serves the WC on (default: a free port); another WC
      connecting there takes over the link
    * `--http-port N` — the dashboard and MTConnect agent (`Vws.Ops.Web`) on port N (default 4000;
      0 picks a free port)
    * `--http-bind ADDR`, `--http-token TOKEN` — as for `mix vws.serve`
    * `--ber RATE`, `--seed N` — put a faulty line (`Vws.Sim.Line`) in every link of the floor,
      the WC's included, flipping each bit with probability RATE, drawn from seed N (default 0):
      the dialogue shows the resends, the summary counts them
    * `--id ID` — the workstation id (default `VWS-DEMO`)
    * `--journal DIR`, `--no-journal` — as for `mix vws.serve`: the journal is on by default, in
      `journal/<id>` of the data directory (`Vws.Ops.DataDir`)
    * `--library DIR`, `--no-library` — likewise the program library (`Vws.CEC.Library`), on by
      default in `library/<id>` of the data directory
    * `--verbose` — keep the application's info logs (by default only warnings interleave with
      the dialogue)

  Without `--once` the shop floor keeps running after the script, until stopped: one Ctrl-C in
  its terminal or `kill PID` stop it in order (`Vws.Ops.Signals`).
  """
  use Mix.Task

  @switches [
    once: :boolean,
    script: :string,
    time_scale: :positive_float,
    wc_port: :port_or_zero,
    http_port: :port_or_zero,
    http_bind: :string,
    http_token: :string,
    id: :string,
    ber: :probability,
    seed: :non_neg_integer,
    verbose: :boolean,
    journal: :string,
    no_journal: :boolean,
    library: :string,
    no_library: :boolean
  ]

  @impl true
  def run(args) do
    opts = Vws.CLIOptions.parse!(args, @switches)
    time_scale = opts[:time_scale] || 1.0

    Mix.Task.run("app.start")
    # one Ctrl-C in this terminal: an ordered stop, never the BEAM's BREAK menu (which freezes it)
    Vws.Ops.Signals.ctrl_c_stops()
    unless opts[:verbose], do: Logger.configure(level: :warning)

    lines =
      case opts[:ber] do
        nil -> false
        ber -> [faults: [ber: ber], seed: opts[:seed] || 0]
      end

    journal =
      try do
        Vws.Ops.DataDir.journal_dir(opts[:id] || "VWS-DEMO", Vws.Ops.DataDir.choice(opts))
      rescue
        ArgumentError -> Mix.raise("--journal DIR and --no-journal exclude each other")
      end

    library =
      try do
        Vws.Ops.DataDir.library_dir(opts[:id] || "VWS-DEMO", Vws.Ops.DataDir.library_choice(opts))
      rescue
        ArgumentError -> Mix.raise("--library DIR and --no-library exclude each other")
      end

    # the floor under the application's equipment supervisor, not linked to this task's process
    # (which ends under `iex -S mix vws.demo`): it stops in order with the application
    demo_opts =
      [
        time_scale: time_scale,
        wc: "tcp://127.0.0.1:#{opts[:wc_port] || 0}",
        lines: lines,
        journal: journal,
        library: library,
        supervisor: Vws.EquipmentSupervisor
      ] ++ Keyword.take(opts, [:script, :id])

    # a WC port that cannot be opened is said before anything starts: "WC port 7070 is in use"
    with {:error, reason} <- Vws.Application.check_wc_port(demo_opts[:wc]),
         do: Mix.raise("the demo did not start: #{Vws.Ops.StartError.describe(reason)}")

    IO.puts("dashboard and MTConnect agent: #{start_web(opts)}")

    case Vws.Ops.Demo.run(demo_opts) do
      {:ok, summary, floor, _client} ->
        completed? = Vws.Peers.WC.Runner.Summary.completed?(summary)
        once? = Keyword.get(opts, :once, false)

        cond do
          once? and completed? ->
            :ok

          once? ->
            exit({:shutdown, 1})

          true ->
            iex? = Code.ensure_loaded?(IEx) and IEx.started?()
            # /health: the floor keeps running, and the node is healthy while its workstation is
            :ok = Vws.Ops.Health.expect(opts[:id] || "VWS-DEMO")

            IO.puts(
              "The shop floor keeps running: SUN_COMM serves the WC on #{floor.wc}. " <>
                Mix.Tasks.Vws.Serve.stop_hint(iex?)
            )

            unless iex?, do: Process.sleep(:infinity)
        end

      {:error, message} ->
        Mix.raise(message)
    end
  end

  defp start_web(opts) do
    case Vws.Ops.Web.start_from_cli(opts) do
      {:ok, url} -> url
      {:error, message} -> Mix.raise(message)
    end
  end
end
