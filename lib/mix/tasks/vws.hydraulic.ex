defmodule Mix.Tasks.Vws.Hydraulic do
  @shortdoc "Runs the hydraulic controller (the HP-9836 program) on its own"
  @moduledoc """
  Runs the hydraulic controller (`Vws.Peers.HydraulicController`) in a node of its own: it listens
  for the CEC's HPIB link and drives the pallet through DAQ #2. A workstation reaches it with
  `mix vws.serve --hydraulic ENDPOINT` (or `devices: [hydraulic: ENDPOINT]`).

      mix vws.hydraulic                                   # CEC on tcp://127.0.0.1:5026, DAQ #2 simulated
      mix vws.hydraulic --listen tcp://0.0.0.0:5026 --cec 10.0.0.2 --daq2 tcp://10.0.0.10:5025
      iex -S mix vws.hydraulic                            # with a shell: Vws.Peers.HydraulicController.info()

  Options:

    * `--listen ENDPOINT` — where the CEC connects (default `tcp://127.0.0.1:5026`)
    * `--cec LIST` — the CEC's address (or addresses/networks, `10.0.0.2,10.0.1.0/24`): only it
      may connect and send commands (default loopback only; required with a `--listen` address
      that is not loopback)
    * `--daq2 ENDPOINT` — DAQ #2 (a LAN SCPI socket, a GPIB gateway). Without it a simulated
      plant and DAQ #2 (`Vws.Sim.Plant`, `Vws.Sim.DAQ`) are started here
    * `--time-scale N` — the simulated plant runs N times faster than real time (default 1)
    * `--min-force N` — the clamp force, in newtons, from which a swing clamp holds (default 4000)
  """
  use Mix.Task

  @switches [
    listen: :string,
    cec: :string,
    daq2: :string,
    time_scale: :positive_float,
    min_force: :pos_integer
  ]

  @impl true
  def run(args) do
    opts = Vws.CLIOptions.parse!(args, @switches)

    Mix.Task.run("app.start")
    # one Ctrl-C in this terminal: an ordered stop, never the BEAM's BREAK menu (which freezes it)
    Vws.Ops.Signals.ctrl_c_stops()

    daq2 = opts[:daq2] || simulated_daq2(opts[:time_scale] || 1.0)
    listen = opts[:listen] || "tcp://127.0.0.1:5026"

    allow =
      with {:ok, allow} <- Vws.Links.Transport.Policy.parse_allow(opts[:cec]),
           :ok <- Vws.Links.Transport.Policy.check_listen(listen, allow) do
        allow
      else
        {:error, message} -> Mix.raise("--listen needs --cec (the CEC's address): " <> message)
      end

    {:ok, sup} =
      Vws.Peers.HydraulicController.start_link(
        [listen: listen, allow: allow, daq2: daq2] ++
          if(opts[:min_force], do: [min_force_n: opts[:min_force]], else: [])
      )

    Process.unlink(sup)
    Mix.shell().info("hydraulic controller: DAQ #2 at #{daq2}; initialising")

    case Vws.Peers.HydraulicController.await_ready(30_000) do
      :ok ->
        info = Vws.Peers.HydraulicController.info()
        Mix.shell().info("hydraulic controller: the CEC connects to #{info.endpoint}")
        Mix.shell().info("start-up: #{start_up(info.init_result)}")

      :timeout ->
        Mix.shell().info("hydraulic controller: still initialising after 30 s")
    end

    unless Code.ensure_loaded?(IEx) and IEx.started?(), do: Process.sleep(:infinity)
  end

  defp simulated_daq2(scale) do
    {:ok, plant} = Vws.Sim.Plant.start_link(time_scale: scale)
    {:ok, daq2} = Vws.Sim.DAQ.start_link(plant: plant, daq: :daq2)
    Process.unlink(plant)
    Process.unlink(daq2)
    endpoint = Vws.Sim.DAQ.endpoint(daq2)
    Mix.shell().info("simulated pallet (time scale ×#{scale}) and DAQ #2 on #{endpoint}")
    endpoint
  end

  defp start_up(:done), do: "depressurised, the swing clamps are released"
  defp start_up({:error, why}), do: "NOT depressurised (#{why}); CLAMP_PALLET depressurises first"
end
