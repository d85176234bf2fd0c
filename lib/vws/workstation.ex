defmodule Vws.Workstation do
  @moduledoc """
  VWS_CONTROL as an OTP tree: one workstation, keyed by its id (a node can run several).

  ```
  Vws.Workstation (rest_for_one)          VWS_CONTROL
  ├── Vws.Mailbox.Owner                   the mailbox table; survives every crash below
  ├── Vws.Journal (optional)              durable log of strings and command statuses; restores them
  ├── links (one_for_one)                 device links, each with its transport
  ├── partitions (one_for_one)            VWS_STATUS, ROBOT, MONARCH, GRIPPER, FIXTURE, VACUUM, HYDRAULIC
  ├── OK_TO_PROCEED                       caused once everything above is up
  └── Vws.SunComm                         the WC link; takes no string before OK_TO_PROCEED
  ```

  What others depend on starts first; a crashed link or partition restarts alone, and SUN_COMM
  keeps its WC connection throughout.

  ## Options

    * `:id` — the workstation id (required)
    * `:wc` — the WC endpoint SUN_COMM serves (`"tcp://127.0.0.1:7070"`, `"tty:/dev/ttyS0?baud=9600"`,
      `"loopback:name"`); `nil` starts SUN_COMM without a link
    * `:journal` — a directory for the command journal (`Vws.Journal`), or its options; none by default
    * `:sun_comm` — further SUN_COMM options (`bcc:`, timeouts; see `Vws.SunComm`)
    * `:links` — child specs of device links, started under the links supervisor
    * `:partitions` — per partition, keyword options: `[robot: [link: …, module: …, options: …]]`
    * `:devices` — equipment by endpoint, each adding its links and partition options (explicit
      `:partitions` options win): `daq1: "tcp://host:5025"` (or `daq1: [endpoint: …, …]`, see
      `Vws.Partitions.VwsStatus.wiring/3`) puts DAQ #1 on the HPIB and links VWS_STATUS, GRIPPER,
      FIXTURE and VACUUM to it, and gives MONARCH its cycle-start relay and ROBOT its tray locks
  """
  use Supervisor

  alias Vws.Mailbox

  @partition_modules [
    robot: Vws.Partitions.Robot,
    monarch: Vws.Partitions.Monarch,
    gripper: Vws.Partitions.Gripper,
    fixture: Vws.Partitions.Fixture,
    vacuum: Vws.Partitions.Vacuum,
    hydraulic: Vws.Partitions.Hydraulic
  ]

  @doc false
  def child_spec(opts) do
    %{
      id: {__MODULE__, Keyword.fetch!(opts, :id)},
      start: {__MODULE__, :start_link, [opts]},
      type: :supervisor,
      restart: :transient
    }
  end

  @spec start_link(keyword) :: Supervisor.on_start()
  def start_link(opts) do
    id = Keyword.fetch!(opts, :id)
    Supervisor.start_link(__MODULE__, opts, name: via(id, :workstation))
  end

  @doc false
  def via(id, role), do: {:via, Registry, {Vws.Registry, {id, role}}}

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :id)
    {device_links, device_partitions} = devices(ws, Keyword.get(opts, :devices, []))
    partition_opts = merge_partitions(device_partitions, Keyword.get(opts, :partitions, []))

    partitions =
      [
        {Vws.Partitions.VwsStatus,
         [workstation: ws] ++ Keyword.get(partition_opts, :vws_status, [])}
      ] ++
        for {p, default_module} <- @partition_modules do
          popts = Keyword.get(partition_opts, p, [])

          {Vws.Partition,
           workstation: ws,
           partition: p,
           module: Keyword.get(popts, :module, default_module),
           link: Keyword.get(popts, :link),
           options: Keyword.get(popts, :options, [])}
        end

    journal =
      case Keyword.get(opts, :journal) do
        nil -> []
        dir when is_binary(dir) -> [{Vws.Journal, workstation: ws, dir: dir}]
        jopts when is_list(jopts) -> [{Vws.Journal, [workstation: ws] ++ jopts}]
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
                 [strategy: :one_for_one, max_restarts: 50, max_seconds: 5, name: via(ws, :links)]
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
                   name: via(ws, :partitions)
                 ]
               ]}
          },
          %{
            id: :ok_to_proceed,
            restart: :transient,
            start: {Task, :start_link, [fn -> :ok = Vws.Events.cause(ws, :ok_to_proceed) end]}
          },
          {Vws.SunComm,
           [workstation: ws, wc: Keyword.get(opts, :wc)] ++ Keyword.get(opts, :sun_comm, [])}
        ]

    Supervisor.init(children, strategy: :rest_for_one, max_restarts: 10, max_seconds: 5)
  end

  # `devices:` — what each device adds: link child specs and partition options.
  defp devices(ws, devices) do
    Enum.reduce(devices, {[], []}, fn {kind, spec}, {links, partitions} ->
      %{links: more_links, partitions: more} = device(ws, kind, spec)
      {links ++ more_links, merge_partitions(partitions, more)}
    end)
  end

  defp device(ws, :daq1, endpoint) when is_binary(endpoint),
    do: Vws.Partitions.VwsStatus.wiring(ws, endpoint)

  defp device(ws, :daq1, opts) when is_list(opts),
    do: Vws.Partitions.VwsStatus.wiring(ws, Keyword.fetch!(opts, :endpoint), opts)

  defp device(_ws, kind, spec),
    do: raise(ArgumentError, "unknown device #{inspect(kind)}: #{inspect(spec)}")

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
      [{pid, _}] -> DynamicSupervisor.terminate_child(Vws.WorkstationSupervisor, pid)
      [] -> {:error, :not_found}
    end
  end

  @doc "The ids of the workstations running on this node."
  @spec list() :: [term]
  def list do
    Registry.select(Vws.Registry, [{{{:"$1", :workstation}, :_, :_}, [], [:"$1"]}]) |> Enum.sort()
  end

  @doc "The pid of a workstation's supervisor or one of its parts (`:links`, `:partitions`, a partition, `:sun_comm`)."
  @spec whereis(term, atom) :: pid | nil
  def whereis(id, role \\ :workstation) do
    case Registry.lookup(Vws.Registry, {id, role}) do
      [{pid, _}] -> pid
      [] -> nil
    end
  end
end
