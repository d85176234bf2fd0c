defmodule Mix.Tasks.Vws.Serve do
  @shortdoc "Starts a VWS workstation and waits for a workstation controller"
  @moduledoc """
  Starts one workstation (VWS_CONTROL, the mailboxes, the partitions and SUN_COMM) and waits for a
  workstation controller. The simulated floor starts first, as the demo's (`Vws.Sim.Floor.start_stocked/1`:
  the plant, DAQ #1, DAQ #2 and the hydraulic controller on it, the GE-2000, the VAL II, the
  material-handling system, a blank in tray #1), without the simulator of each device given an
  endpoint (`--daq1`, `--hydraulic`, `--ge2000`, `--robot`), and the workstation is connected to
  it: `mix vws.wc --script priv/sims/machining_cycle.vws` runs the shipped cycle against it.

      mix vws.serve                       # WC on tcp://127.0.0.1:7070
      mix vws.serve --wc-port 7071 --bind 0.0.0.0 --wc-allow 10.0.0.5   # only the WC at 10.0.0.5
      mix vws.serve --wc tty:/dev/ttyUSB0?baud=9600
      mix vws.serve --time-scale 10       # the simulated plant ten times faster
      mix vws.serve --daq1 tcp://10.0.0.9:5025   # a real DAQ #1 (LAN SCPI socket): no simulators
      mix vws.serve --ge2000 tty:/dev/ttyS1?baud=4800   # the real VMC instead of the simulator
      mix vws.serve --hydraulic tcp://10.0.0.12:5026    # a hydraulic controller of its own (mix vws.hydraulic)
      iex -S mix vws.serve                # the same, with a shell to inspect it live
      mix vws.serve --http-port 8080      # the dashboard and MTConnect agent on another port
      mix vws.serve --journal /var/lib/vws/journal   # the command journal there (default: see below)

  Options:

    * `--wc-port N` — TCP port for the WC (default 7070)
    * `--bind ADDR` — address to listen on (default 127.0.0.1)
    * `--wc-allow LIST` — the addresses/networks that may connect to the WC port
      (`10.0.0.5,10.0.0.0/24`; default `$VWS_WC_ALLOW`, else loopback only). Required to listen
      anywhere but loopback (`Vws.Links.Transport.Policy`; the link's policy: `Vws.CEC.SunComm`)
    * `--wc ENDPOINT` — any endpoint instead (`tcp://host:port`, `tty:/dev/…?baud=…`, `loopback:name`)
    * `--id ID` — the workstation id (default `VWS`)
    * `--journal DIR` — the command journal (every command status, the NC file and NC_UP, kept
      across a restart or a `kill -9`: `Vws.CEC.Journal`) in DIR. By default it is on, in
      `$VWS_JOURNAL_DIR`, else `journal/<id>` of the data directory (`$VWS_DATA_DIR`, else
      `$XDG_STATE_HOME/vws`, else `~/.local/state/vws`; see `Vws.Ops.DataDir`)
    * `--no-journal` — no journal: a restart forgets every command
    * `--library DIR` — the program library (`Vws.CEC.Library`: every program DOWNLOAD_HP brought,
      with its versions; `mix vws.library`) in DIR. By default `$VWS_LIBRARY_DIR`, else
      `library/<id>` of the data directory
    * `--no-library` — no program library
    * `--bcc sum|xor` — the WC link's block check (default sum)
    * `--time-scale N` — the simulated plant runs N times faster than real time (default 1)
    * `--daq1 ENDPOINT` — DAQ #1 is real equipment there; the plant and DAQ #1 are not simulated
    * `--daq1-port N` — the TCP port the simulated DAQ #1 listens on (default: a free port)
    * `--http-port N` — the dashboard and MTConnect agent (`Vws.Ops.Web`) on port N (default 4000;
      0 picks a free port)
    * `--http-bind ADDR` — the address they listen on (default 127.0.0.1)
    * `--http-token-file PATH` — enables the dashboard's control actions for requests carrying
      the token in this file (mode 0600; default: the file in `$VWS_HTTP_TOKEN_FILE`, else
      `$VWS_HTTP_TOKEN`, else none: read-only). A token is never given on the command line,
      where every local user reads it (`ps`): `--http-token TOKEN` is refused
    * `--http-read-token-file PATH` — every read (dashboard, `/api/state`, MTConnect) needs the
      token in this file too (HTTP Basic password or `x-vws-token`; default: the file in
      `$VWS_HTTP_READ_TOKEN_FILE`, else `$VWS_HTTP_READ_TOKEN`, else none: reads open);
      `--http-read-token TOKEN` is refused (`Vws.Ops.Web.Tokens`)
    * `--robot ENDPOINT` — the VAL II's supervisory port (`tty:/dev/ttyS1?baud=9600`, a terminal
      server's `tcp://host:port`); without it a simulated VAL II (`Vws.Sim.VAL2`) is started on a
      free local port and ROBOT is connected to it
    * `--robot-time-scale F` — the simulated robot's motion time factor (default 1.0)
    * `--ge2000 ENDPOINT` — the real GE-2000's DNC port (`tty:/dev/ttyS1?baud=4800`, a terminal
      server's `tcp://host:port`). Without it a simulated GE-2000 (`Vws.Sim.GE2000`) is started on
      a free local port and connected; its cycle-start button stands in for the DAQ #1 relay.
    * `--ge2000-baud N` — pace the simulated GE-2000's line at N Bd (default: unpaced)
    * `--dnc-profile PROFILE` — what the machine tool's DNC port speaks
      (`Vws.Links.ProgramPort.Profile`): `ge2000-level2` (default) or `rs232-xonxoff`, a plain
      RS-232 control under XON/XOFF (`Vws.Links.RS232`, docs/serial.md). Without `--ge2000`, the
      latter starts a simulated control of that kind (`Vws.Sim.RS232Control`) instead of the
      GE-2000, which punches every program it keeps back (the operator's read-back a download
      needs to end DONE); with it, the real control's port is reached that way
    * `--hydraulic ENDPOINT` — the hydraulic controller's HPIB endpoint, e.g. one started on another
      node or machine with `mix vws.hydraulic`. Without it the hydraulic controller
      (`Vws.Peers.HydraulicController`) runs in this node on the simulated plant's DAQ #2.
  """
  use Mix.Task

  @switches [
    wc_port: :port_or_zero,
    bind: :string,
    wc_allow: :string,
    wc: :string,
    id: :string,
    bcc: {:in, ["sum", "xor"]},
    time_scale: :positive_float,
    daq1: :string,
    daq1_port: :port_or_zero,
    robot: :string,
    robot_time_scale: :positive_float,
    ge2000: :string,
    ge2000_baud: :pos_integer,
    dnc_profile: :string,
    hydraulic: :string,
    http_port: :port_or_zero,
    http_bind: :string,
    http_token: :string,
    http_token_file: :string,
    journal: :string,
    no_journal: :boolean,
    library: :string,
    no_library: :boolean,
    http_read_token: :string,
    http_read_token_file: :string
  ]

  @impl true
  def run(args) do
    opts = Vws.CLIOptions.parse!(args, @switches)
    opts = http_tokens(opts)

    # config/runtime.exs starts a workstation of its own when VWS_WC is set (a release's way):
    # this task starts the one it is asked for instead, so that one must not start too
    # (it collided: {:error, {:already_started, _}})
    Mix.Task.run("app.config")
    Application.delete_env(:vws, :workstation)
    Mix.Task.run("app.start")
    # one Ctrl-C in this terminal: an ordered stop, never the BEAM's BREAK menu (which freezes it)
    Vws.Ops.Signals.ctrl_c_stops()

    wc = opts[:wc] || "tcp://#{opts[:bind] || "127.0.0.1"}:#{opts[:wc_port] || 7070}"

    with {:error, e} <- Vws.Links.Endpoint.parse(wc),
         do: Mix.raise("#{if opts[:wc], do: "--wc", else: "--bind"}: #{Exception.message(e)}")

    id = opts[:id] || "VWS"
    journal = Vws.Ops.DataDir.journal_dir(id, journal_choice(opts))

    library =
      try do
        Vws.Ops.DataDir.library_dir(id, Vws.Ops.DataDir.library_choice(opts))
      rescue
        ArgumentError -> Mix.raise("--library DIR and --no-library exclude each other")
      end

    allow = wc_allow(wc, opts[:wc_allow] || System.get_env("VWS_WC_ALLOW"))

    bcc = if opts[:bcc] == "xor", do: :xor, else: :sum

    # a WC port that cannot be opened is said before anything starts: "WC port 7070 is in use"
    with {:error, reason} <- Vws.Application.check_wc_port(wc),
         do: Mix.raise("workstation #{id} did not start: #{Vws.Ops.StartError.describe(reason)}")

    opts = Keyword.put(opts, :dnc_profile, dnc_profile(opts[:dnc_profile]))
    floor = floor_devices(id, opts)
    robot = robot(id, opts)
    {ge2000, monarch} = ge2000(id, opts)
    devices = [ge2000: [endpoint: ge2000, profile: opts[:dnc_profile]], robot: robot] ++ floor

    # a simulated GE-2000's own button is MONARCH's cycle start; else the DAQ #1 relay is
    case Vws.CEC.Workstation.start(
           id: id,
           wc: wc,
           sun_comm: [bcc: bcc, allow: allow],
           devices: devices,
           partitions: [monarch: [options: monarch]],
           journal: journal,
           library: library
         ) do
      {:ok, _} -> :ok
      {:error, reason} -> Mix.raise("workstation #{id} did not start: #{start_error(reason)}")
    end

    # its port taken meanwhile: SUN_COMM stops, and so does this task, in words
    with {:error, reason} <- Vws.Application.await_wc(id, wc, 10_000),
         do: Mix.raise("workstation #{id} did not start: #{start_error(reason)}")

    # /health: this node is healthy while this workstation runs with its links up
    :ok = Vws.Ops.Health.expect(id)
    listening = Vws.CEC.SunComm.await_listening(id, 1_000)
    Mix.shell().info("VWS workstation #{id}: SUN_COMM waits for the WC on #{listening || wc}")
    Mix.shell().info("GE-2000 DNC link: #{ge2000} (profile #{profile_name(opts[:dnc_profile])})")

    Mix.shell().info(
      "Journal: #{journal || "none (--no-journal): a restart forgets every command"}"
    )

    Mix.shell().info("Program library: #{library || "none (--no-library)"}")
    Mix.shell().info("Dashboard and MTConnect agent: #{start_web(opts)}")
    Mix.shell().info("Inspect it: Vws.Ops.Inspect.overview(#{inspect(id)})")
    Mix.shell().info(stop_hint(iex_running?()))

    unless iex_running?(), do: Process.sleep(:infinity)
  end

  # Who may connect to the WC port: refused here, with the reason, rather than by SUN_COMM later.
  defp wc_allow(wc, text) do
    with {:ok, allow} <- Vws.Links.Transport.Policy.parse_allow(text),
         :ok <- Vws.Links.Transport.Policy.check_listen(wc, allow) do
      allow
    else
      {:error, message} -> Mix.raise("the WC port: " <> message)
    end
  end

  # The simulated floor, as the demo's (Vws.Sim.Floor.start_stocked/1: the plant, material
  # handling, a blank in tray #1) with a simulator for each device not given (--daq1,
  # --hydraulic, --ge2000, --robot): the robot's motions and the machine's cycle reach the plant,
  # so priv/sims/machining_cycle.vws runs against it. DAQ #1 and the hydraulic controller's
  # endpoints are returned; robot/2 and ge2000/2 say theirs. The floor runs under the
  # application's equipment supervisor, not linked to this task's process: under `iex -S mix
  # vws.serve` that process ends once the task has run (and took the floor with it), and the
  # application stops it in order — after the workstation, before the registry it is named in.
  defp floor_devices(id, opts) do
    sim_daq1 = opts[:daq1] == nil
    sim_hydraulic = opts[:hydraulic] == nil

    if sim_daq1 or sim_hydraulic or opts[:robot] == nil or opts[:ge2000] == nil do
      scale = opts[:time_scale] || 1.0

      {:ok, _} =
        Vws.Sim.Floor.start_stocked(
          supervisor: Vws.EquipmentSupervisor,
          workstation: id,
          time_scale: scale,
          daq1: sim_daq1 && "tcp://127.0.0.1:#{opts[:daq1_port] || 0}",
          daq2: sim_hydraulic && "tcp://127.0.0.1:0",
          hydraulic: sim_hydraulic && {Vws.Peers.HydraulicController, []},
          robot: opts[:robot] == nil && [time_scale: opts[:robot_time_scale] || 1.0],
          ge2000:
            opts[:ge2000] == nil and opts[:dnc_profile] == :ge2000_level2 &&
              [pace: opts[:ge2000_baud] || false]
        )

      Mix.shell().info(
        "simulated plant (time scale ×#{scale}), material handling, a blank in tray #1"
      )
    end

    daq1 =
      if sim_daq1 do
        endpoint = Vws.Sim.Floor.daq1_endpoint(id)
        Mix.shell().info("simulated DAQ #1 on #{endpoint}")
        endpoint
      else
        Mix.shell().info("DAQ #1: #{opts[:daq1]}")
        opts[:daq1]
      end

    hydraulic =
      if sim_hydraulic do
        endpoint = Vws.Sim.Floor.hydraulic_endpoint(id)

        Mix.shell().info(
          "hydraulic controller on #{endpoint}, its DAQ #2 simulated on #{Vws.Sim.Floor.daq2_endpoint(id)}"
        )

        endpoint
      else
        Mix.shell().info("hydraulic controller: #{opts[:hydraulic]}")
        opts[:hydraulic]
      end

    [daq1: daq1, hydraulic: hydraulic]
  end

  # the real VAL II, or the floor's simulated one (equipment: outside the workstation)
  defp robot(id, opts) do
    case opts[:robot] do
      nil ->
        endpoint = Vws.Sim.VAL2.endpoint(Vws.Sim.Floor.robot(id))
        Mix.shell().info("Simulated VAL II robot controller on #{endpoint}")
        endpoint

      endpoint ->
        Mix.shell().info("ROBOT connects to the VAL II at #{endpoint}")
        endpoint
    end
  end

  # The real machine's endpoint, or the floor's simulator (its button stands in for the relay).
  defp ge2000(id, opts) do
    case {opts[:ge2000], opts[:dnc_profile]} do
      {nil, :rs232_xonxoff} ->
        # the operator stand-in: every program kept is punched back (a download's read-back)
        {:ok, sim} =
          DynamicSupervisor.start_child(
            Vws.EquipmentSupervisor,
            {Vws.Sim.RS232Control, punch_after_load: true}
          )

        endpoint = Vws.Sim.RS232Control.endpoint(sim)
        Mix.shell().info("Simulated RS-232 control (XON/XOFF) on #{endpoint}")
        {endpoint, []}

      {nil, _} ->
        sim = Vws.Sim.Floor.ge2000(id)
        Mix.shell().info("Simulated GE-2000 on #{Vws.Sim.GE2000.endpoint(sim)}")
        {Vws.Sim.GE2000.endpoint(sim), [cycle_start: fn -> Vws.Sim.GE2000.cycle_start(sim) end]}

      {endpoint, _} ->
        {endpoint, []}
    end
  end

  # an unknown profile is said before anything starts
  defp dnc_profile(nil), do: :ge2000_level2

  defp dnc_profile(name) do
    case Vws.Links.ProgramPort.Profile.parse(name) do
      {:ok, profile} -> profile
      {:error, message} -> Mix.raise("--dnc-profile: " <> message)
    end
  end

  defp profile_name(profile), do: profile |> Atom.to_string() |> String.replace("_", "-")

  defp journal_choice(opts) do
    Vws.Ops.DataDir.choice(opts)
  rescue
    ArgumentError -> Mix.raise("--journal DIR and --no-journal exclude each other")
  end

  # why a workstation did not start, in words: the innermost reason of the supervisor's
  # failed child (a journal directory in use by another OS process, a port taken, …)
  defp start_error(reason), do: Vws.Ops.StartError.describe(reason)

  defp iex_running?, do: Code.ensure_loaded?(IEx) and IEx.started?()

  @doc false
  # How to stop it cleanly (Vws.Ops.Signals): one Ctrl-C when the terminal is ours
  # (Signals.ctrl_c_stops/0), else Ctrl-\\ (SIGQUIT); SIGTERM always. The BEAM's BREAK menu (Ctrl-C
  # where the terminal could not be taken) stops nothing in order.
  def stop_hint(iex?) do
    how =
      cond do
        Vws.Ops.Signals.ctrl_c_mapped?() and iex? -> "Ctrl-C, System.stop()"
        Vws.Ops.Signals.ctrl_c_mapped?() -> "Ctrl-C"
        iex? -> "System.stop() or Ctrl-\\"
        true -> "Ctrl-\\"
      end

    "Stop: #{how} or kill #{System.pid()} (in order)"
  end

  # The tokens from files or the environment (Vws.Ops.Web.Tokens), never from the command line:
  # there every local user reads them (`ps`, /proc/<pid>/cmdline).
  defp http_tokens(opts) do
    for {key, flag, file_flag, var} <- [
          {:http_token, "--http-token", "--http-token-file", "VWS_HTTP_TOKEN"},
          {:http_read_token, "--http-read-token", "--http-read-token-file", "VWS_HTTP_READ_TOKEN"}
        ],
        Keyword.has_key?(opts, key) do
      Mix.raise(
        "#{flag} puts the token on the command line, where every local user can read it " <>
          "(ps): write it to a file only you can read (chmod 0600) and give #{file_flag} PATH, " <>
          "or set #{var}_FILE (the file) or #{var} (the token) in the environment"
      )
    end

    token = fn
      {:ok, token} -> token
      {:error, message} -> Mix.raise(message)
    end

    opts
    |> Keyword.put(:http_token, token.(Vws.Ops.Web.Tokens.control(opts[:http_token_file])))
    |> Keyword.put(:http_read_token, token.(Vws.Ops.Web.Tokens.read(opts[:http_read_token_file])))
  end

  defp start_web(opts) do
    case Vws.Ops.Web.start_from_cli(opts) do
      {:ok, url} -> url
      {:error, message} -> Mix.raise(message)
    end
  end
end
