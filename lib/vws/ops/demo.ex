defmodule Vws.Ops.Demo do
  @moduledoc """
  The demonstration behind `mix vws.demo`: a workstation with its shop floor, a workstation
  controller (`Vws.Peers.WC.Client`) running a cycle script (`Vws.Peers.WC.Script`) against it, and the
  dialogue printed as it happens.

  ## The shop floor

  `start_shop_floor/1` is the one place that decides what runs: the simulated equipment first,
  then the workstation with a link to each simulator. `shop_floor/1` starts the whole floor
  (`Vws.Sim.Floor`): the plant with DAQ #1 (VWS_STATUS, GRIPPER, FIXTURE and VACUUM reach it;
  ROBOT gets its tray locks, MONARCH its cycle-start relay), DAQ #2 with the hydraulic controller
  (HYDRAULIC), the GE-2000 (whose cycle-start input is that relay), the VAL II robot and the
  material-handling system, with a blank in tray #1 — and turns where the floor's devices are
  (`Vws.Sim.Floor.devices/1`) into the workstation's links and partition options
  (`Vws.CEC.Workstation.device_links/3`). A partition whose device is not on the floor starts
  without a device link and answers each valid command `ERROR NO LINK TO <device>` —
  truthfully — and a cycle stops at its first such command.

  ## The printed dialogue

  As `Vws.Peers.WC.Printer` prints it (as `mix vws.wc --script` does): one row per line on the
  link, script steps on rows of their own, a status query answered as the previous one folded.
  """

  alias Vws.Peers.WC.{Client, Printer, Runner, Script}
  alias Vws.Peers.WC.Runner.Summary

  @type shop_floor :: %{
          workstation: term,
          wc: String.t(),
          time_scale: number,
          simulated: [String.t()],
          lines: [atom],
          unlinked: [{atom, String.t()}]
        }

  @doc """
  Starts the shop floor: every simulator there is, then a workstation linked to them, whose
  SUN_COMM serves the WC at `:wc`. Options: `:id` (default `"VWS-DEMO"`), `:wc` (default
  `"tcp://127.0.0.1:0"`, a free port), `:time_scale` (default 1.0; the simulators run this many
  times faster than real time), `:bcc`, `:lines` (faulty cables on every link, the WC's included:
  `[faults: [ber: 1.0e-4, …], seed: term]`, see `Vws.Sim.Floor`; `Vws.Sim.Floor.line(id, :wc)` is
  the WC's), `:supervisor` (a `DynamicSupervisor` to start the floor and the WC's line under;
  by default they are linked to the caller), `:journal` (the journal's directory, none by
  default; `mix vws.demo` gives one), `:library` (the program library's directory, likewise),
  `:ge2000` and `:devices` (see `shop_floor/1`: the GE-2000 simulator on a serial line, and the
  workstation reaching it through a terminal server). Returns where the WC reaches SUN_COMM
  (through its line, if any), what is simulated, which links have a faulty line and which
  partitions have no device link.
  """
  @spec start_shop_floor(keyword) :: {:ok, shop_floor} | {:error, term}
  def start_shop_floor(opts \\ []) do
    id = Keyword.get(opts, :id, "VWS-DEMO")
    wc = Keyword.get(opts, :wc, "tcp://127.0.0.1:0")
    time_scale = Keyword.get(opts, :time_scale, 1.0)
    lines = Keyword.get(opts, :lines, false)

    sim_opts =
      [workstation: id, time_scale: time_scale, lines: lines] ++
        Keyword.take(opts, [:supervisor, :ge2000, :devices])

    with {:ok, sim} <- shop_floor(sim_opts),
         {:ok, _pid} <-
           Vws.CEC.Workstation.start(
             id: id,
             wc: wc,
             sun_comm: [bcc: Keyword.get(opts, :bcc, :sum)],
             journal: Keyword.get(opts, :journal),
             library: Keyword.get(opts, :library),
             links: sim.links,
             partitions: sim.partitions
           ),
         {:ok, listening} <- wait_listening(id, 2_000),
         {:ok, wc} <- wc_line(id, to_string(listening), lines, opts[:supervisor]) do
      unlinked =
        for {partition, module} <- Vws.CEC.Workstation.partition_modules(),
            Vws.CEC.Partition.info(id, partition).link == nil,
            do: {partition, module.device()}

      {:ok,
       %{
         workstation: id,
         wc: wc,
         time_scale: time_scale,
         lines: Keyword.keys(Vws.Sim.Floor.lines(id)),
         simulated: [sim.name],
         unlinked: unlinked
       }}
    end
  end

  @doc """
  The demo's shop floor: starts the whole simulated floor (`Vws.Sim.Floor.start_stocked/1`:
  linked to the caller, or under the `DynamicSupervisor` given as `:supervisor`) with the
  `:workstation`, `:time_scale`, `:seed` and `:lines` given — hydraulic controller, GE-2000,
  VAL II, material handling — and a blank in tray #1, and returns the workstation links and
  partition options that reach it (`Vws.CEC.Workstation.device_links/3` of
  `Vws.Sim.Floor.devices/1`). `{:error, {Vws.Sim.Floor, reason}}` when the floor does not start.

  Two options put something real between the workstation and a simulator: `:ge2000` — the
  GE-2000 simulator's options (`Vws.Sim.GE2000`, e.g. `endpoint: "tty:/dev/pts/7"`: it opens
  that serial line instead of listening) — and `:devices` — where the workstation reaches a
  device instead of where the floor says it is (a keyword list as the workstation's `devices:`
  takes it, e.g. `ge2000: "rfc2217://127.0.0.1:2001?baud=38400"`, a terminal server whose port is
  cabled to that line).
  """
  @spec shop_floor(keyword) ::
          {:ok, %{name: String.t(), links: [Supervisor.child_spec()], partitions: keyword}}
          | {:error, {module, term}}
  def shop_floor(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    floor =
      Keyword.take(opts, [:workstation, :time_scale, :seed, :lines, :supervisor]) ++
        [
          hydraulic: {Vws.Peers.HydraulicController, []},
          ge2000: Keyword.get(opts, :ge2000, true),
          robot: true,
          mhs: true
        ]

    case Vws.Sim.Floor.start_stocked(floor) do
      {:ok, _pid} ->
        devices = Keyword.merge(Vws.Sim.Floor.devices(ws), Keyword.get(opts, :devices, []))
        {links, partitions} = Vws.CEC.Workstation.device_links(ws, devices, [])

        {:ok,
         %{
           name:
             "plant + DAQ #1 + DAQ #2 + hydraulic controller, GE-2000, VAL II, material handling",
           links: links,
           partitions: partitions
         }}

      {:error, reason} ->
        {:error, {Vws.Sim.Floor, reason}}
    end
  end

  # with faulty lines on the floor, the WC reaches SUN_COMM through one too
  defp wc_line(_id, sun_comm, false, _supervisor), do: {:ok, sun_comm}

  defp wc_line(id, sun_comm, lines, supervisor) do
    line_opts = [
      name: Vws.Sim.Floor.line(id, :wc),
      target: sun_comm,
      seed: {Keyword.get(lines, :seed, 0), :wc},
      faults: Keyword.get(lines, :faults, [])
    ]

    started =
      if supervisor,
        do: DynamicSupervisor.start_child(supervisor, {Vws.Sim.Line, line_opts}),
        else: Vws.Sim.Line.start_link(line_opts)

    with {:ok, line} <- started, do: {:ok, to_string(Vws.Sim.Line.endpoint(line))}
  end

  defp wait_listening(id, timeout) do
    case Vws.CEC.SunComm.await_listening(id, timeout) do
      nil -> {:error, :sun_comm_not_listening}
      endpoint -> {:ok, endpoint}
    end
  end

  @doc """
  The default cycle script: `priv/sims/machining_cycle.vws` of the project (`sims_script/1`).
  """
  @spec default_script() :: Path.t()
  def default_script, do: sims_script("machining_cycle.vws")

  @doc """
  A shipped script, `priv/sims/<name>`: in the current directory when it is there (a checkout),
  else in the application's priv directory (a release).
  """
  @spec sims_script(String.t()) :: Path.t()
  def sims_script(name) do
    local = Path.join("priv/sims", name)
    if File.regular?(local), do: local, else: Application.app_dir(:vws, local)
  end

  @doc """
  Starts the shop floor, connects a WC, runs the script and prints the dialogue and the summary
  to the group leader. Options: `:script` (a path, default `default_script/0`), `:id`, `:wc`,
  `:time_scale` (see `start_shop_floor/1`) and the `Vws.Peers.WC.Runner` options. Returns the summary,
  the shop floor and the client, which stay up for the caller.
  """
  @spec run(keyword) :: {:ok, Summary.t(), shop_floor, Client.client()} | {:error, String.t()}
  def run(opts \\ []) do
    path = Keyword.get_lazy(opts, :script, &default_script/0)

    with {:script, {:ok, script}} <- {:script, Script.parse_file(path)},
         {:floor, {:ok, floor}} <- {:floor, start_shop_floor(opts)},
         {:client, {:ok, client}} <- {:client, Client.connect(floor.wc, subscribe: self())} do
      print_floor(floor, path, script)
      summary = run_printing(client, script, opts)
      Enum.each(Summary.format(summary), &IO.puts(Printer.readable(&1)))
      {:ok, summary, floor, client}
    else
      {:script, {:error, error}} -> {:error, Exception.message(error)}
      {:floor, {:error, reason}} -> {:error, "cannot start the shop floor: #{inspect(reason)}"}
      {:client, {:error, reason}} -> {:error, "the WC cannot connect: #{inspect(reason)}"}
    end
  end

  defp print_floor(floor, path, script) do
    IO.puts(
      "VWS demo — workstation #{floor.workstation}, " <>
        if(floor.lines == [],
          do: "SUN_COMM serves the WC on #{floor.wc}",
          else: "the WC reaches SUN_COMM through a faulty line on #{floor.wc}"
        )
    )

    simulated =
      if floor.simulated == [], do: "nothing yet", else: Enum.join(floor.simulated, ", ")

    IO.puts("simulated equipment: #{simulated} (time scale ×#{scale(floor.time_scale)})")

    if floor.lines != [],
      do: IO.puts("faulty lines (Vws.Sim.Line) on the links: #{Enum.join(floor.lines, ", ")}")

    for {partition, device} <- floor.unlinked do
      IO.puts(
        "  #{String.upcase(to_string(partition))} has no link to the #{device}: " <>
          "its commands end ERROR NO LINK TO #{device}"
      )
    end

    IO.puts("script: #{path} (#{length(script.steps)} steps)")
    IO.puts("")
    IO.puts("   time   line on the WC link (→ WC to CEC, ← CEC to WC)           meaning")
  end

  defp run_printing(client, script, opts) do
    task = Task.async(fn -> Runner.run(client, script, opts) end)
    {printer, summary} = print_until(task, client, Printer.new())
    # every event the client sent before answering this call is already in our mailbox
    _ = Client.info(client)
    printer = drain(client, printer)
    Printer.flush(printer)
    IO.puts("")
    summary
  end

  defp print_until(%Task{ref: ref} = task, client, printer) do
    receive do
      {:wc_client, ^client, event} ->
        print_until(task, client, Printer.print_event(event, printer))

      {^ref, summary} ->
        Process.demonitor(ref, [:flush])
        {printer, summary}
    end
  end

  defp drain(client, printer) do
    receive do
      {:wc_client, ^client, event} -> drain(client, Printer.print_event(event, printer))
    after
      0 -> printer
    end
  end

  defp scale(x) when is_float(x) and x == trunc(x), do: trunc(x)
  defp scale(x), do: x
end
