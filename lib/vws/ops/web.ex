defmodule Vws.Ops.Web do
  @moduledoc """
  The node's web server, a small bounded HTTP/1.1 server of its own on `:gen_tcp`
  (`Vws.Ops.Web.Server`; no hex packages): the live dashboard and
  the MTConnect agent: the dashboard details every workstation of the node and lists every
  workstation of the cell with its node and state; the agent serves every workstation of the cell
  (`Vws.CEC.Cell`), each read on its own node.

  | path | what |
  |------|------|
  | `GET /` | the dashboard: one page, updated from `/api/state` every 400 ms |
  | `GET /api/state` | every workstation's partitions, devices, interlocks, links and WC dialogue, as JSON |
  | `POST /api/status?ws=ID&name=NAME` | a control action: asks a status command (header `x-vws-token`) |
  | `GET /probe`, `/current`, `/sample?from=&count=` | MTConnect 2.5 (`Vws.Ops.MTConnect.Agent`) |
  | `GET /<device>/probe` … | the same for one device (a workstation id) |

  It binds 127.0.0.1 unless told otherwise. It is read-only unless a `:token` is configured:
  a control request without the token, or with a wrong one, is answered 403 before its body is
  read. With a `:read_token` every read needs a token too (HTTP Basic password or `x-vws-token`;
  see `Vws.Ops.Web.Handler`). Request sizes, connections and timeouts are bounded
  (`Vws.Ops.Web.Server`).

  Every request emits the telemetry event `[:vws, :web, :request]` (measurements `duration`,
  `bytes`; metadata `method, path, status, port`).

      {:ok, web} = Vws.Ops.Web.start_link(port: 4000)
      Vws.Ops.Web.url(web)   #=> "http://127.0.0.1:4000/"

  ## Options

    * `:port` — TCP port (default 4000; 0 picks a free one, see `port/1`)
    * `:bind` — address to listen on (default `"127.0.0.1"`)
    * `:token` — the token control actions need (default none: read-only)
    * `:read_token` — the token every read needs (default none: reads open)
    * `:max_connections`, `:max_client_connections`, `:max_client_connect_rate`, `:max_rate`,
      `:max_client_rate`, `:max_wait`, `:max_body`, `:max_line`, `:max_headers`, `:max_head`,
      `:head_timeout`, `:idle_timeout`, `:body_timeout`, `:max_requests`, `:send_timeout` — the
      server's limits (`Vws.Ops.Web.Server`)
    * `:state_max_age` — ms the `/api/state` answer is reused for (`Vws.Ops.Web.Snapshot`, 200)
    * `:buffer_size`, `:checkpoint_frequency`, `:interval`, `:node_timeout` — the MTConnect agent's (see
      `Vws.Ops.MTConnect.Agent`)
    * `:name` — a name for the server's supervisor
  """
  use Supervisor

  @doc false
  def child_spec(opts) do
    %{
      id: Keyword.get(opts, :name, __MODULE__),
      start: {__MODULE__, :start_link, [opts]},
      type: :supervisor
    }
  end

  @doc "Starts the web server (its MTConnect agent, then the HTTP listener)."
  @spec start_link(keyword) :: Supervisor.on_start()
  def start_link(opts \\ []) do
    ref = make_ref()

    case Keyword.get(opts, :name) do
      nil -> Supervisor.start_link(__MODULE__, {ref, opts})
      name -> Supervisor.start_link(__MODULE__, {ref, opts}, name: name)
    end
  end

  @doc "Starts the web server under the application's supervisor (for `mix vws.serve`/`vws.demo`)."
  @spec start(keyword) :: DynamicSupervisor.on_start_child()
  def start(opts), do: DynamicSupervisor.start_child(Vws.WebSupervisor, {__MODULE__, opts})

  @doc """
  Starts the web server from the command-line options of `mix vws.serve` and `mix vws.demo`
  (`http_port` default 4000, `http_bind` default 127.0.0.1, `http_token` default
  `$VWS_HTTP_TOKEN`, `http_read_token` default `$VWS_HTTP_READ_TOKEN`). Returns the dashboard's URL, or a message saying why it could not start.
  """
  @spec start_from_cli(keyword) :: {:ok, String.t()} | {:error, String.t()}
  def start_from_cli(opts) do
    port = Keyword.get(opts, :http_port, 4000)
    bind = Keyword.get(opts, :http_bind, "127.0.0.1")
    token = Keyword.get_lazy(opts, :http_token, fn -> System.get_env("VWS_HTTP_TOKEN") end)

    read_token =
      Keyword.get_lazy(opts, :http_read_token, fn -> System.get_env("VWS_HTTP_READ_TOKEN") end)

    case start(port: port, bind: bind, token: token, read_token: read_token) do
      {:ok, web} ->
        mode = if token in [nil, ""], do: "read-only", else: "control actions need the token"
        reads = if read_token in [nil, ""], do: "", else: ", reads need the read token"
        {:ok, "#{url(web)} (#{mode}#{reads})"}

      {:error, reason} ->
        {:error,
         "the dashboard cannot start: #{Vws.Ops.StartError.describe(reason)}; " <>
           "choose another port with --http-port N"}
    end
  end

  @impl true
  def init({ref, opts}) do
    agent = Vws.Names.via({__MODULE__, ref}, :agent)
    connections = Vws.Names.via({__MODULE__, ref}, :connections)
    snapshot = Vws.Names.via({__MODULE__, ref}, :snapshot)
    control = opts[:token] not in [nil, ""]
    max = Keyword.get(opts, :max_connections, Vws.Ops.Web.Server.defaults()[:max_connections])

    # the node's recent events for the page: one per node, outliving any one server. Started
    # aside: this may run inside Vws.WebSupervisor's own start_child (Web.start/1)
    unless Process.whereis(Vws.Ops.Web.History), do: spawn(&Vws.Ops.Web.History.ensure_started/0)

    children = [
      {Vws.Ops.MTConnect.Agent,
       [name: agent] ++
         Keyword.take(opts, [
           :buffer_size,
           :checkpoint_frequency,
           :interval,
           :node_timeout,
           :workstations
         ])},
      # the connections are counted and bounded by the server's admission (Vws.Ops.Web.Clients),
      # which closes idle ones to make room: a closed one may not be reaped yet when the next
      # starts, hence the margin; this bound is only a backstop
      # (at low priority, as the connections and the agent: HTTP work yields to the workstations)
      {Task.Supervisor, name: connections, max_children: 2 * max, spawn_opt: [priority: :low]},
      {Vws.Ops.Web.Server,
       [ref: ref, agent: agent, snapshot: snapshot, connections: connections] ++ opts},
      # last: were it to fail, the listener (and its port) stays as it is
      {Vws.Ops.Web.Snapshot,
       [name: snapshot, control: control] ++
         if(opts[:state_max_age], do: [max_age: opts[:state_max_age]], else: [])}
    ]

    Supervisor.init(children, strategy: :rest_for_one)
  end

  @doc "The TCP port the server listens on."
  @spec port(Supervisor.supervisor()) :: :inet.port_number()
  def port(web), do: web |> server() |> Vws.Ops.Web.Server.port()

  @doc """
  The HTTP connections open: `{total, %{client => count}}` (a client is a peer address, an IPv6
  one by its /64).
  """
  @spec connections(Supervisor.supervisor()) :: {non_neg_integer, map}
  def connections(web), do: web |> server() |> Vws.Ops.Web.Server.connections()

  @doc "The dashboard's URL (`http://ADDR:PORT/`)."
  @spec url(Supervisor.supervisor()) :: String.t()
  def url(web), do: web |> server() |> Vws.Ops.Web.Server.url()

  defp server(web) do
    Enum.find_value(Supervisor.which_children(web), fn
      {Vws.Ops.Web.Server, pid, _, _} when is_pid(pid) -> pid
      _ -> nil
    end) || raise ArgumentError, "the web server is not running"
  end
end
