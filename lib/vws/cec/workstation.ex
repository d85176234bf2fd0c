defmodule Vws.CEC.Workstation do
  @moduledoc """
  VWS_CONTROL as an OTP tree: one workstation, keyed by its id (a node can run several).

  ```
  Vws.CEC.Workstation (rest_for_one)          VWS_CONTROL
  ├── Vws.CEC.Mailbox.Owner                   the mailbox table; survives every crash below
  ├── Vws.CEC.Journal (optional)              durable log of strings and command statuses; restores them
  ├── links (one_for_one)                 device links, each with its transport
  ├── partitions (one_for_one)            VWS_STATUS, ROBOT, MONARCH, GRIPPER, FIXTURE, VACUUM, HYDRAULIC
  ├── OK_TO_PROCEED                       caused once everything above is up
  └── Vws.CEC.SunComm                         the WC link; takes no string before OK_TO_PROCEED
  ```

  What others depend on starts first; a crashed link or partition restarts alone, and SUN_COMM
  keeps its WC connection throughout. The supervisor joins the cell (`Vws.CEC.Cell`) under its id
  as it starts, so every node of the cell can find it. Its parts are registered in
  `Vws.Registry` as `{id, role}` (`whereis/2`).

  ## Options

    * `:id` — the workstation id (required)
    * `:wc` — the WC endpoint SUN_COMM serves (`"tcp://127.0.0.1:7070"`, `"tty:/dev/ttyS0?baud=9600"`,
      `"loopback:name"`); `nil` starts SUN_COMM without a link
    * `:journal` — a directory for the command journal (`Vws.CEC.Journal`), or its options; none by default
    * `:library` — the directory of the workstation's program library (`Vws.CEC.Library`): DOWNLOAD_HP
      stores every program there, `DOWNLOAD_GE(nnnnnn.PRO)` sends from it; none by default
    * `:sun_comm` — further SUN_COMM options (`bcc:`, timeouts; see `Vws.CEC.SunComm`)
    * `:links` — child specs of device links, started under the links supervisor
    * `:devices` — device endpoints turned into links (see `device_links/3`):
      `[ge2000: "tcp://host:port"]` adds the DNC link to the GE-2000 and gives it to MONARCH;
      `[robot: "tcp://host:port"]` adds a `Vws.Links.VAL` (with its `Vws.Links.DDCMP` link) and gives it to ROBOT;
      `[daq1: "tcp://host:5025"]` puts DAQ #1 on the HPIB, links VWS_STATUS, GRIPPER, FIXTURE and
      VACUUM to it, and gives MONARCH its cycle-start relay and ROBOT its tray locks;
      `[hydraulic: "tcp://host:port"]` puts the hydraulic controller on the HPIB and links HYDRAULIC
      and the PALLET status to it
    * `:partitions` — per partition, keyword options: `[robot: [link: …, module: …, options: …]]`;
      a stand-in `module:` (a test double, the scale benchmark's obedient partitions) whose
      commands are not the seed's sets says `interlocks: :off` — the partitions' own modules
      always go through the interlock table (`Vws.CEC.Interlock.Rules`), and `:off` with one of
      them raises

  `start_link/1` checks these options, and the `sun_comm:` ones against `Vws.CEC.SunComm`'s schema,
  before anything starts: an unknown option or a bad value raises `Vws.Options.Error` naming it
  (`start/1` returns it as `{:error, {%Vws.Options.Error{}, stacktrace}}`).
  """
  use Supervisor

  alias Vws.CEC.Mailbox
  alias Vws.Names

  @partition_modules [
    robot: Vws.Partitions.Robot,
    monarch: Vws.Partitions.Monarch,
    gripper: Vws.Partitions.Gripper,
    fixture: Vws.Partitions.Fixture,
    vacuum: Vws.Partitions.Vacuum,
    hydraulic: Vws.Partitions.Hydraulic
  ]

  @doc """
  The command partitions of a workstation and the module each runs by default (a stand-in may
  be given as a partition's `:module`), in the order they start.
  """
  @spec partition_modules() :: [{Vws.CEC.Mailbox.partition(), module}]
  def partition_modules, do: @partition_modules

  @doc false
  def child_spec(opts) do
    %{
      id: {__MODULE__, Keyword.fetch!(opts, :id)},
      start: {__MODULE__, :start_link, [opts]},
      type: :supervisor,
      restart: :transient
    }
  end

  @schema [
    id: [type: :any, required: true],
    wc: [type: {:or, [nil, :string]}, default: nil],
    journal: [type: {:or, [nil, :string, :keyword_list]}, default: nil],
    library: [type: {:or, [nil, :string]}, default: nil],
    sun_comm: [type: :keyword_list, default: []],
    links: [type: :list, default: []],
    devices: [type: :keyword_list, default: []],
    partitions: [type: :keyword_list, default: []]
  ]

  @spec start_link(keyword) :: Supervisor.on_start()
  def start_link(opts) do
    opts = Vws.Options.validate!(opts, @schema, "workstation")
    # SUN_COMM's options too, here in the caller, once: its child gets them checked
    sun_comm =
      Vws.CEC.SunComm.validate_options!(
        [workstation: opts[:id], wc: opts[:wc]] ++ opts[:sun_comm]
      )

    opts = Keyword.put(opts, :sun_comm, sun_comm)
    Supervisor.start_link(__MODULE__, opts, name: Names.via(opts[:id], :workstation))
  end

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :id)
    # a member of the cell (Vws.CEC.Cell) for as long as this supervisor lives
    :ok = Vws.CEC.Cell.join(ws)
    # the program library's directory, found by the workstation's id while it runs
    :ok = Vws.CEC.Library.register(ws, Keyword.get(opts, :library))

    {device_links, partition_opts} =
      device_links(ws, Keyword.get(opts, :devices, []), Keyword.get(opts, :partitions, []))

    partitions =
      [
        {Vws.Partitions.VwsStatus,
         [workstation: ws, devices: configured(opts, partition_opts)] ++
           Keyword.get(partition_opts, :vws_status, [])}
      ] ++
        for {p, default_module} <- @partition_modules do
          popts = Keyword.get(partition_opts, p, [])
          module = Keyword.get(popts, :module, default_module)
          interlocks = Keyword.get(popts, :interlocks, :on)

          if interlocks not in [:on, :off] or (interlocks == :off and module == default_module),
            do:
              raise(
                ArgumentError,
                "partition #{p}: interlocks: #{inspect(interlocks)} (only a stand-in module may be :off)"
              )

          {Vws.CEC.Partition,
           workstation: ws,
           partition: p,
           module: module,
           interlocks: interlocks,
           link: Keyword.get(popts, :link),
           options: Keyword.get(popts, :options, [])}
        end

    journal =
      case Keyword.get(opts, :journal) do
        nil -> []
        dir when is_binary(dir) -> [{Vws.CEC.Journal, workstation: ws, dir: dir}]
        jopts when is_list(jopts) -> [{Vws.CEC.Journal, [workstation: ws] ++ jopts}]
      end

    children =
      [{Mailbox.Owner, workstation: ws}] ++
        journal ++
        [
          %{
            id: :links,
            type: :supervisor,
            start:
              {Supervisor, :start_link,
               [
                 Keyword.get(opts, :links, []) ++ device_links,
                 [
                   strategy: :one_for_one,
                   max_restarts: 50,
                   max_seconds: 5,
                   name: Names.via(ws, :links)
                 ]
               ]}
          },
          %{
            id: :partitions,
            type: :supervisor,
            start:
              {Supervisor, :start_link,
               [
                 partitions,
                 [
                   strategy: :one_for_one,
                   max_restarts: 50,
                   max_seconds: 5,
                   name: Names.via(ws, :partitions)
                 ]
               ]}
          },
          # caused here, in the start sequence, before SUN_COMM starts: a process started to
          # cause it could run after SUN_COMM, and start/1 return before SUN_COMM had it
          %{id: :ok_to_proceed, restart: :transient, start: {__MODULE__, :ok_to_proceed, [ws]}},
          Vws.CEC.SunComm.child_spec({:validated, Keyword.fetch!(opts, :sun_comm)})
        ]

    Supervisor.init(children, strategy: :rest_for_one, max_restarts: 10, max_seconds: 5)
  end

  @doc false
  # OK_TO_PROCEED, caused as a step of the supervisor's start sequence (a child that starts no
  # process): everything above it is up, SUN_COMM below it finds the event already caused.
  def ok_to_proceed(ws) do
    :ok = Vws.CEC.Events.cause(ws, :ok_to_proceed)
    :ignore
  end

  # The devices this workstation has a link to: named in `devices:`, or reached through a
  # partition's own `link:` (as `mix vws.demo` gives them) — so that their locations say
  # "NOT READ YET" rather than "NO LINK" (the demo's robot read NO DATA (NO LINK TO VAL II)
  # while it worked).
  defp configured(opts, partition_opts) do
    linked =
      for {partition, device} <- [robot: :robot, monarch: :ge2000, hydraulic: :hydraulic],
          Keyword.get(Keyword.get(partition_opts, partition, []), :link) != nil,
          do: device

    Enum.uniq(Keyword.keys(Keyword.get(opts, :devices, [])) ++ linked)
  end

  @doc """
  The link children for the `devices:` option, and the partition options updated to use them.

  `ge2000: [endpoint: …, profile: "rs232-xonxoff", …more Vws.Links.RS232 options]` adds a plain
  RS-232 port instead (`Vws.Links.ProgramPort.Profile`; docs/serial.md): no status reads, and
  MONARCH is told the profile (its option `:profile`).

  `ge2000: endpoint` (or `ge2000: [endpoint: …, …more Vws.Links.DNC options]`) adds a `Vws.Links.DNC` link
  registered as `{ws, :ge2000}` (`whereis(ws, :ge2000)`) and the `Vws.Partitions.Monarch.Monitor`
  that keeps the MONARCH status current through it (`status_interval:` ms, default 1 000;
  `nil`: no reads, the monitor then only owns the link so that programs sent from the machine are
  kept), and makes the link MONARCH's `link:` unless the partition options name one.

  `robot: endpoint` (or `robot: [endpoint: …, ddcmp: […more Vws.Links.DDCMP options]]`) adds a
  `Vws.Links.VAL` registered as `{ws, :val}`, which starts its own `Vws.Links.DDCMP` link to the VAL II, and
  makes it ROBOT's `link:` unless the partition options name one.

  `daq1: endpoint` (or `daq1: [endpoint: …, …]`) puts DAQ #1 on the HPIB and merges in the
  partition options of `Vws.Partitions.VwsStatus.wiring/3` (explicit ones win).

  `hydraulic: endpoint` (or `hydraulic: [endpoint: …, …]`) puts the hydraulic controller on the
  HPIB with the PALLET monitor and merges in the options of `Vws.Partitions.Hydraulic.wiring/3`.
  """
  @spec device_links(term, keyword, keyword) ::
          {[Supervisor.child_spec() | {module, term}], keyword}
  def device_links(ws, devices, partition_opts) do
    Enum.reduce(devices, {[], partition_opts}, fn
      {:ge2000, spec}, {links, popts} ->
        link_opts = if is_binary(spec), do: [endpoint: spec], else: spec
        {interval, link_opts} = Keyword.pop(link_opts, :status_interval, 1_000)
        # the port's profile names its link (Vws.Links.ProgramPort); a plain RS-232 control
        # has no status report to read
        {profile, link_opts} = port_profile(link_opts)
        interval = if profile == :ge2000_level2, do: interval
        name = Names.via(ws, :ge2000)
        module = Vws.Links.ProgramPort.Profile.link_module(profile)
        link = {module, [id: :ge2000, name: name] ++ link_opts}

        # always there: it owns the link (programs from the machine); reads only with an interval
        monitor = [
          {Vws.Partitions.Monarch.Monitor, workstation: ws, link: name, interval: interval}
        ]

        monarch =
          Keyword.get(popts, :monarch, [])
          |> Keyword.put_new(:link, name)
          |> Keyword.update(:options, [profile: profile], &Keyword.put_new(&1, :profile, profile))

        {links ++ [link | monitor], Keyword.put(popts, :monarch, monarch)}

      {:robot, spec}, {links, popts} ->
        spec = if is_binary(spec), do: [endpoint: spec], else: spec

        ddcmp =
          Keyword.merge(Keyword.get(spec, :ddcmp, []), endpoint: spec[:endpoint], workstation: ws)

        name = Names.via(ws, :val)

        val =
          {Vws.Links.VAL,
           [id: :val, name: name, ddcmp: ddcmp] ++ Keyword.take(spec, [:link_module])}

        robot = Keyword.put_new(Keyword.get(popts, :robot, []), :link, name)
        {links ++ [val], Keyword.put(popts, :robot, robot)}

      {:daq1, spec}, {links, popts} ->
        %{links: more, partitions: wired} = daq1(ws, spec)
        {links ++ more, merge_partitions(wired, popts)}

      {:hydraulic, spec}, {links, popts} ->
        %{links: more, partitions: wired} = hydraulic(ws, spec)
        {links ++ more, merge_partitions(wired, popts)}

      {device, _spec}, _acc ->
        raise ArgumentError,
              "unknown device #{inspect(device)} (known: :ge2000, :robot, :daq1, :hydraulic)"
    end)
  end

  defp port_profile(link_opts) do
    {profile, link_opts} = Keyword.pop(link_opts, :profile, :ge2000_level2)

    case Vws.Links.ProgramPort.Profile.parse(profile) do
      {:ok, profile} -> {profile, link_opts}
      {:error, message} -> raise ArgumentError, "devices: ge2000: " <> message
    end
  end

  # DAQ #1 on the HPIB: its link and the partition options that reach it.
  defp daq1(ws, endpoint) when is_binary(endpoint),
    do: Vws.Partitions.VwsStatus.wiring(ws, endpoint)

  defp daq1(ws, opts) when is_list(opts),
    do: Vws.Partitions.VwsStatus.wiring(ws, Keyword.fetch!(opts, :endpoint), opts)

  # The hydraulic controller on the HPIB: its link, the PALLET monitor, HYDRAULIC's link.
  defp hydraulic(ws, endpoint) when is_binary(endpoint),
    do: Vws.Partitions.Hydraulic.wiring(ws, endpoint)

  defp hydraulic(ws, opts) when is_list(opts),
    do: Vws.Partitions.Hydraulic.wiring(ws, Keyword.fetch!(opts, :endpoint), opts)

  # Partition options merged per partition, and their `options:` merged too; `right` wins.
  defp merge_partitions(left, right) do
    Keyword.merge(left, right, fn _partition, l, r ->
      Keyword.merge(l, r, fn
        :options, lo, ro -> Keyword.merge(lo, ro)
        _key, _lv, rv -> rv
      end)
    end)
  end

  @doc "Starts a workstation under the node's workstation supervisor."
  @spec start(keyword) :: DynamicSupervisor.on_start_child()
  def start(opts),
    do: DynamicSupervisor.start_child(Vws.WorkstationSupervisor, {__MODULE__, opts})

  @doc "Stops a workstation started with `start/1`."
  @spec stop(term) :: :ok | {:error, :not_found}
  def stop(id) do
    case Registry.lookup(Vws.Registry, {id, :workstation}) do
      [{pid, _}] ->
        _ = Vws.CEC.Cell.leave(id, pid)
        DynamicSupervisor.terminate_child(Vws.WorkstationSupervisor, pid)

      [] ->
        {:error, :not_found}
    end
  end

  ## Equipment outside the CEC

  @outside_holders [:mhs]

  @doc """
  Asks for a work volume on behalf of equipment outside the CEC that shares it — the
  material-handling system before it moves a tray (seed §2.3.8, rules 2a and 2b) — by the same
  procedure the partitions use (`Vws.CEC.Interlock.acquire/5`; options `:retry_ms`). This is what
  such equipment (`Vws.Sim.MHS`) may do, and all: it holds leases only in its own name (`:mhs`),
  never a partition's, and a workstation that is not running grants nothing
  (`{:error, "NO ANSWER FROM THE CEC"}`).
  """
  @spec acquire_volume(term, Vws.CEC.Interlock.volume(), atom, non_neg_integer, keyword) ::
          :ok | {:error, String.t()}
  def acquire_volume(ws, volume, holder, timeout, opts \\ []) when holder in @outside_holders do
    if Mailbox.exists?(ws) do
      Vws.CEC.Interlock.acquire(ws, volume, holder, timeout, Keyword.take(opts, [:retry_ms]))
    else
      {:error, "NO ANSWER FROM THE CEC"}
    end
  rescue
    # the mailboxes went away between the look and the lease: the workstation is stopping
    ArgumentError -> {:error, "NO ANSWER FROM THE CEC"}
  end

  @doc "Gives back a work volume taken with `acquire_volume/5`."
  @spec release_volume(term, Vws.CEC.Interlock.volume(), atom) :: :ok
  def release_volume(ws, volume, holder) when holder in @outside_holders do
    if Mailbox.exists?(ws), do: Vws.CEC.Interlock.release(ws, volume, holder), else: :ok
  end

  @doc "The ids of the workstations running on this node (`Vws.Names.workstations/0`)."
  @spec list() :: [term]
  defdelegate list, to: Names, as: :workstations

  @doc "The pid of a workstation's supervisor or one of its parts (`:links`, `:partitions`, a partition, `:sun_comm`)."
  @spec whereis(term, atom) :: pid | nil
  defdelegate whereis(id, role \\ :workstation), to: Names
end
