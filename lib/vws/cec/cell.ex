defmodule Vws.CEC.Cell do
  @moduledoc """
  The cell: every workstation on every node connected by Erlang distribution, found through
  `:pg` — no clustering of our own.

  The application starts the `:pg` scope `#{inspect(:vws_cell)}` (`child_spec/1`), and each
  workstation supervisor joins the group `{:workstation, id}` when it starts (`join/1`, from
  `Vws.CEC.Workstation`'s `init/1`); it leaves the group when it stops, as `:pg` forgets a process
  that exits. Nothing here is on the path of a WC string: only start-up and the cell view touch
  `:pg`. How nodes find each other (`Node.connect/1`, `-name`, libcluster in a deployment) is
  Erlang's business; `:pg` merges its groups whenever nodes connect.

  ## The cell view

  `workstations/0` lists every workstation of the cell, each with its node and its state,
  asking each node once (`:erpc`) about its own workstations; `Vws.Ops.Inspect.cell/0` prints it
  in iex, the dashboard (`Vws.Ops.Web`) shows it too, and the MTConnect agent (`Vws.Ops.MTConnect.Agent`) serves
  every workstation of the cell (`locations/0`) as a device:

      iex> {:ok, _} = Vws.CEC.Workstation.start(id: "doc-cell", wc: "loopback:doc-cell")
      iex> Vws.CEC.Cell.whereis("doc-cell") == Vws.CEC.Workstation.whereis("doc-cell")
      true
      iex> [ws] = Enum.filter(Vws.CEC.Cell.workstations(), &(&1.id == "doc-cell"))
      iex> ws.node == node()
      true
      iex> Vws.CEC.Workstation.stop("doc-cell")
      :ok
      iex> Vws.CEC.Cell.whereis("doc-cell")
      nil

  A workstation's `state` is `:starting` (OK_TO_PROCEED not yet caused, or SUN_COMM
  restarting), `:idle` (no command in flight), `:busy` (a partition has a command in flight) or
  `:unreachable` (its node did not answer).

  ## Reaching a workstation's WC link from anywhere

  `wc_endpoint/1` gives `cell:<id>`, which `Vws.Peers.WC.Client.connect/2` (or any caller of
  `connect/2` here) dials from any node of the cell. The transports know nothing of the cell:
  `connect/2` resolves `cell:` endpoints through `Vws.CEC.Cell.Connection` and passes every other
  endpoint to `Vws.Links.Transport.connect/2` as it is. Connecting resolves the id now —
  so a client that reopens its link finds the workstation again, wherever it was restarted —
  and then:

    * SUN_COMM listening on `loopback:` (a node may serve a thousand workstations that way
      without a socket): the connection is a loopback pair started on the caller's node and
      handed to SUN_COMM's listener on the workstation's node; the bytes travel as Erlang
      messages over distribution;
    * SUN_COMM listening on `tcp://`: a plain TCP connection to it (`0.0.0.0` replaced by the
      host of the workstation's node);
    * SUN_COMM on a tty: the WC is on the serial line; `{:error, :not_reachable}`.

  Either way the bytes on the WC link are exactly those of a direct connection.

  When two nodes run a workstation with the same id, `workstations/0` lists both and
  `whereis/1` (and so `cell:<id>`) prefers the one on the caller's node, else the first by pid.
  """

  alias Vws.Links.Endpoint
  alias Vws.CEC.Mailbox

  @scope :vws_cell
  @rpc_timeout 5_000

  @type state :: :starting | :idle | :busy | :unreachable
  @type workstation :: %{
          required(:id) => term,
          required(:node) => node,
          required(:state) => state,
          optional(:wc) => String.t() | nil,
          optional(:wc_connected) => boolean,
          optional(:commands) => %{Mailbox.partition() => {0..9999 | nil, Mailbox.status()}}
        }

  @doc "The `:pg` scope of the cell, started by the application."
  @spec child_spec(term) :: Supervisor.child_spec()
  def child_spec(_opts), do: %{id: __MODULE__, start: {:pg, :start_link, [@scope]}}

  @doc "The name of the cell's `:pg` scope."
  @spec scope() :: atom
  def scope, do: @scope

  @doc "Makes the calling process (a workstation's supervisor) the cell's member for `id`."
  @spec join(term) :: :ok
  def join(id), do: :pg.join(@scope, group(id), self())

  @doc false
  # Called by `Vws.CEC.Workstation.stop/1` before the supervisor is stopped: `:pg` would only drop it
  # when it sees it die, after `stop/1` has returned, and `whereis/1` would name a dead process.
  @spec leave(term, pid) :: :ok | :not_joined
  def leave(id, pid), do: :pg.leave(@scope, group(id), pid)

  @doc """
  The pid of workstation `id`'s supervisor, on whichever node of the cell it runs (the local
  one first), or nil.
  """
  @spec whereis(term) :: pid | nil
  def whereis(id) do
    case :pg.get_members(@scope, group(id)) do
      [] -> nil
      pids -> pick(pids)
    end
  end

  @doc """
  Where each workstation of the cell runs: `{id, node}`, one per id (the node `whereis/1` finds),
  sorted by id.
  """
  @spec locations() :: [{term, node}]
  def locations do
    for {:workstation, id} = group <- :pg.which_groups(@scope),
        pids = :pg.get_members(@scope, group),
        pids != [] do
      {id, node(pick(pids))}
    end
    |> Enum.sort()
  end

  # The member `whereis/1` means when two nodes run a workstation with the same id.
  defp pick(pids), do: Enum.find(pids, &(node(&1) == node())) || Enum.min(pids)

  @doc "The ids and supervisor pids of every workstation of the cell, sorted by id and node."
  @spec members() :: [{term, pid}]
  def members do
    for {:workstation, id} = group <- :pg.which_groups(@scope),
        pid <- :pg.get_members(@scope, group) do
      {id, pid}
    end
    |> Enum.sort_by(fn {id, pid} -> {id, node(pid)} end)
  end

  @doc """
  Every workstation of the cell: `%{id, node, state, wc, wc_connected, commands}` — `wc` the
  endpoint SUN_COMM serves, `wc_connected` whether a WC is on it, `commands` the last command of
  each set and its status. A node that does not answer within `timeout` ms lists its
  workstations as `:unreachable` with only `id`, `node` and `state`.
  """
  @spec workstations(timeout) :: [workstation]
  def workstations(timeout \\ @rpc_timeout) do
    members = members()
    nodes = members |> Enum.map(fn {_id, pid} -> node(pid) end) |> Enum.uniq()

    answers =
      Enum.zip(nodes, :erpc.multicall(nodes, __MODULE__, :local_workstations, [], timeout))

    for {n, answer} <- answers do
      ids = for {id, pid} <- members, node(pid) == n, do: id

      case answer do
        {:ok, infos} ->
          # a workstation that stopped in between is not listed; one that started is
          infos

        _failed ->
          for id <- ids, do: %{id: id, node: n, state: :unreachable}
      end
    end
    |> List.flatten()
    |> Enum.sort_by(&{&1.id, &1.node})
  end

  @doc false
  # Called on each node by workstations/1: this node's members of the cell.
  @spec local_workstations() :: [workstation]
  def local_workstations do
    for {:workstation, id} = group <- :pg.which_groups(@scope),
        :pg.get_local_members(@scope, group) != [] do
      local_info(id)
    end
  end

  defp local_info(id) do
    sun_comm =
      try do
        Vws.CEC.SunComm.info(id)
      catch
        :exit, _ -> nil
      end

    commands =
      try do
        Map.new(Mailbox.partitions(), &{&1, Mailbox.command_status(id, &1)})
      rescue
        _ -> %{}
      catch
        :exit, _ -> %{}
      end

    state =
      cond do
        sun_comm == nil or not sun_comm.ok_to_proceed -> :starting
        Enum.any?(commands, fn {_p, {_n, status}} -> status == :executing end) -> :busy
        true -> :idle
      end

    %{
      id: id,
      node: node(),
      state: state,
      wc: sun_comm && sun_comm.listening && to_string(sun_comm.listening),
      wc_connected: sun_comm != nil and sun_comm.peer != nil,
      commands: commands
    }
  end

  @doc """
  The endpoint a WC dials to reach workstation `id` from any node of the cell: `cell:<id>`
  (see the moduledoc), or `{:error, :not_found}` when no node of the cell runs it.
  """
  @spec wc_endpoint(term) :: {:ok, Endpoint.t()} | {:error, :not_found}
  def wc_endpoint(id) do
    if whereis(id),
      do: {:ok, %Endpoint{kind: :cell, name: id}},
      else: {:error, :not_found}
  end

  @doc """
  Connects to `endpoint` as `Vws.Links.Transport.connect/2` does, resolving a `cell:<id>` endpoint
  first (see the moduledoc): the WC link of that workstation wherever it runs in the cell.
  Errors of a cell endpoint: `:not_found`, `:not_listening` (a client retries), `:not_reachable`,
  or those of the transport reached.
  """
  @spec connect(Vws.Links.Transport.endpoint(), keyword) ::
          {:ok, Vws.Links.Transport.Conn.t()} | {:error, term}
  def connect(endpoint, opts \\ []) do
    case endpoint do
      %Endpoint{kind: :cell} -> connect_cell(endpoint, opts)
      "cell:" <> _ -> connect_cell(endpoint, opts)
      _ -> Vws.Links.Transport.connect(endpoint, opts)
    end
  end

  defp connect_cell(endpoint, opts),
    do:
      Vws.Links.Transport.connect(
        endpoint,
        Keyword.put(opts, :transport, Vws.CEC.Cell.Connection)
      )

  @doc """
  Where workstation `id`'s SUN_COMM listens: its node and the endpoint it is bound to.
  `{:error, :not_found}` when no node runs it, `{:error, :not_listening}` while SUN_COMM is not
  (yet) listening or not running.
  """
  @spec resolve(term, timeout) ::
          {:ok, node, Endpoint.t()} | {:error, :not_found | :not_listening}
  def resolve(id, timeout \\ @rpc_timeout) do
    with pid when is_pid(pid) <- whereis(id) || {:error, :not_found} do
      n = node(pid)

      listening =
        try do
          if n == node(),
            do: Vws.CEC.SunComm.listening(id),
            else: :erpc.call(n, Vws.CEC.SunComm, :listening, [id], timeout)
        catch
          _, _ -> nil
        end

      if listening, do: {:ok, n, listening}, else: {:error, :not_listening}
    end
  end

  defp group(id), do: {:workstation, id}
end
