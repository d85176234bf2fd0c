defmodule Vws.Ops.Web.Server do
  @moduledoc """
  A small, bounded HTTP/1.1 server on OTP's `:socket` — the listener of `Vws.Ops.Web`.

  OTP's `:inets` httpd, which served the dashboard before, reads a whole request body before its
  modules see the request, has no limit on the URI, and queues every client beyond `max_clients`
  for as long as the ones it holds stay open: 50 idle connections stopped the dashboard for
  150 s, and a 300 MB POST that was answered 403 grew the node by 600 MB. This server gives the
  guarantees instead (decisions; each one is an option, defaults in brackets):

    * the request line and each header line at most `:max_line` bytes [8192], CR LF included,
      at most `:max_headers` headers [64] and `:max_head` bytes of head in all [32 768]: a
      longer request line is answered 414, a longer header line, too many headers or too large
      a head 431, and the connection is closed (the rest of the head is read and dropped for at
      most a second, so that the client reads the answer; it is never kept);
    * the whole head (request line and headers) must arrive within `:head_timeout` ms [10 000]
      of the connection's first request, or of the end of the previous answer on a kept-alive
      connection within `:idle_timeout` ms [5 000] — a client that is idle or trickles a byte
      at a time is closed when its time is up, whatever it sends;
    * a body at most `:max_body` bytes [65 536], only with `Content-Length` (a chunked body
      answers 411), read within `:body_timeout` ms [10 000] — and read only **after** the
      request has been authorized (`Vws.Ops.Web.Handler.authorize/2`): a refused request is answered
      at once and the connection closed, its body never read;
    * at most `:max_connections` open connections [1024], and at most `:max_client_connections`
      [64] from one client (a peer address; an IPv6 client by its /64). Before a newcomer is
      refused, room is made (`Vws.Ops.Web.Clients`): a client at its share loses its own
      connection idle the longest; a full server closes the connection idle the longest of any
      client (waiting for a head: kept-alive between requests, never sent one, or trickling it),
      else the oldest stream of the client holding the most connections, if it holds more than
      the newcomer would. Only when nothing can be closed is the newcomer answered 503 at once
      and closed (it never waits in a queue);
    * while the server holds half its connections or more, at most `:max_client_connect_rate` new
      connections a second from one client [10, and 20 at once after a quiet while]: one more is
      answered 503 at once and closes nobody — a client
      reconnecting as fast as it is closed costs a bounded amount of work;
    * at most `:max_requests` requests per kept-alive connection [100]; an answer that the client
      does not read within `:send_timeout` ms [10 000] closes the connection;
    * at most `:max_client_rate` requests a second from one client [50, and 50 at once after a
      quiet second; the dashboard asks 2.5 a second per open page], and `:max_rate` in all
      [500]: a request beyond them waits its turn (the client is held, not sent away to come
      straight back), and one that would wait more than `:max_wait` ms [10 000] is answered
      503. One client flooding waits behind its own requests and takes at most its own rate of
      the server's. Each part of a stream counts as a request;
    * an MTConnect stream (`interval=`) runs beside its connection's process, which watches the
      socket (`active: :once`): when the client closes or resets it the stream ends at once,
      whatever it was waiting for, and the socket is closed (no connection is left in CLOSE-WAIT
      until the next part). `interval` and `heartbeat` are at most 10 s (`Vws.Ops.Web.Handler`).
      HTTP load is so bounded in CPU and
      socket work whatever the number of clients, which is what keeps the WC's answers on time
      (`bench/http_load.exs`).

  Each connection is a process of its own (under a `Task.Supervisor`; admitted and counted by
  `Vws.Ops.Web.Clients`) reading passively with timeouts from a raw socket; the head is parsed line by
  line by OTP's HTTP parser (`:erlang.decode_packet/3`, the one of `packet: :http_bin`) from a
  buffer that never holds more than `:max_line` bytes and one read of the socket, and the bytes
  after it — a body, or the next request of a client that pipelines — are kept for what follows
  (`Vws.Ops.Web.Conn`). Acceptors and connections run at low process priority, so the
  workstations' own processes — SUN_COMM answering its WC first of all — are scheduled before any
  HTTP work (`bench/http_load.exs` measures it). Their sockets are OTP's `:socket` itself:
  accepting, reading, writing and closing are NIF calls made by those low-priority processes and
  no other. `:gen_tcp` with its default `inet_drv` does them as port tasks, scheduled beside every
  process and outside the reductions that share a scheduler among processes; `:gen_tcp` on the
  socket backend (`inet_backend: :socket`) moves them into one `gen_tcp_socket` server per
  socket, which OTP starts at normal priority. Under 2,000 hostile sockets coming and going,
  `inet_drv` put the WC's p99 at 3–4 times that of a listener in another OS process
  (`bench/http_hostile.exs`); the MTConnect agent, the admission server (`Vws.Ops.Web.Clients`),
  the state snapshot and the connections' supervisor run at low priority for the same reason.
  """
  use GenServer
  require Logger
  alias Vws.Ops.Web.Clients

  @acceptors 4

  @defaults [
    max_line: 8192,
    max_headers: 64,
    max_head: 32_768,
    head_timeout: 10_000,
    idle_timeout: 5_000,
    max_body: 65_536,
    body_timeout: 10_000,
    max_connections: 1024,
    max_client_connections: 64,
    max_client_connect_rate: 10,
    max_requests: 100,
    send_timeout: 10_000,
    max_rate: 500,
    max_client_rate: 50,
    max_wait: 10_000
  ]

  @doc "The limits and timeouts the server applies unless told otherwise."
  @spec defaults() :: keyword
  def defaults, do: @defaults

  @doc false
  def child_spec(opts), do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}}

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts), do: GenServer.start_link(__MODULE__, opts)

  @doc "The port the server listens on."
  @spec port(pid) :: :inet.port_number()
  def port(server), do: GenServer.call(server, :port)

  @doc """
  The connections open: `{total, %{client => count}}` (a client is a peer address; an IPv6
  client is its /64).
  """
  @spec connections(pid) :: {non_neg_integer, %{tuple => pos_integer}}
  def connections(server), do: server |> GenServer.call(:clients) |> Clients.count()

  @doc "The dashboard's URL."
  @spec url(pid) :: String.t()
  def url(server), do: GenServer.call(server, :url)

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    bind = Keyword.get(opts, :bind, "127.0.0.1")

    with {:ok, address} <- parse_address(bind),
         limits = Keyword.merge(@defaults, Keyword.take(opts, Keyword.keys(@defaults))),
         {:ok, socket} <- listen(address, Keyword.get(opts, :port, 4000)) do
      {:ok, %{port: port}} = :socket.sockname(socket)
      url = "http://#{host(bind)}:#{port}/"

      settings = %{
        agent: Keyword.fetch!(opts, :agent),
        snapshot: Keyword.fetch!(opts, :snapshot),
        token: blank_to_nil(opts[:token]),
        read_token: blank_to_nil(opts[:read_token]),
        port: port
      }

      limits = Map.new(limits)
      {:ok, clients} = Vws.Ops.Web.Clients.start_link(limits)

      conf = %{
        settings: settings,
        limits: limits,
        connections: Keyword.fetch!(opts, :connections),
        clients: clients,
        tables: Vws.Ops.Web.Clients.tables(clients),
        # the time (µs, monotonic) from which the next request may be served, all clients
        # together (each client has its own too: Vws.Ops.Web.Clients)
        pace: Vws.Ops.Web.Clients.pace_cell()
      }

      acceptors = for _ <- 1..@acceptors, do: spawn_link(fn -> accept_loop(socket, conf) end)

      Logger.info(
        "VWS web server on #{url} (#{mode(settings)}; at most #{limits[:max_connections]} connections)"
      )

      {:ok, %{socket: socket, port: port, url: url, acceptors: acceptors, clients: clients}}
    else
      {:error, reason} -> {:stop, {:cannot_listen, bind, opts[:port], reason}}
    end
  end

  defp mode(%{token: nil, read_token: nil}), do: "read-only, reads open"
  defp mode(%{token: nil}), do: "read-only, reads need the read token"
  defp mode(%{read_token: nil}), do: "control with token, reads open"
  defp mode(_), do: "control with token, reads need a token"

  defp parse_address(bind) do
    case :inet.parse_address(String.to_charlist(bind)) do
      {:ok, address} -> {:ok, address}
      {:error, _} -> {:error, {:bad_address, bind}}
    end
  end

  # (the send timeout is each send's own: Vws.Ops.Web.Conn)
  defp listen(address, port) do
    family = if tuple_size(address) == 8, do: :inet6, else: :inet

    with {:ok, socket} <- :socket.open(family, :stream, :tcp) do
      with :ok <- :socket.setopt(socket, {:socket, :reuseaddr}, true),
           :ok <- :socket.bind(socket, %{family: family, addr: address, port: port}),
           :ok <- :socket.listen(socket, 1024) do
        {:ok, socket}
      else
        error ->
          :socket.close(socket)
          error
      end
    end
  end

  defp host(bind) do
    if String.contains?(bind, ":"), do: "[#{bind}]", else: bind
  end

  defp blank_to_nil(nil), do: nil
  defp blank_to_nil(""), do: nil
  defp blank_to_nil(token) when is_binary(token), do: token

  @impl true
  def handle_call(:port, _from, s), do: {:reply, s.port, s}
  def handle_call(:url, _from, s), do: {:reply, s.url, s}
  def handle_call(:clients, _from, s), do: {:reply, s.clients, s}

  @impl true
  def handle_info({:EXIT, pid, reason}, s) do
    cond do
      pid in s.acceptors -> {:stop, {:acceptor_down, reason}, s}
      pid == s.clients -> {:stop, {:clients_down, reason}, s}
      true -> {:noreply, s}
    end
  end

  def handle_info(_msg, s), do: {:noreply, s}

  @impl true
  def terminate(_reason, %{socket: socket}) do
    :socket.close(socket)
    :ok
  end

  ## Acceptors

  defp accept_loop(listen_socket, conf) do
    Process.flag(:priority, :low)

    case :socket.accept(listen_socket) do
      {:ok, socket} ->
        _ = :socket.setopt(socket, {:tcp, :nodelay}, true)
        # one read of the socket, and so what a connection's buffer holds beyond `max_line`
        _ = :socket.setopt(socket, {:otp, :rcvbuf}, 4096)
        hand_over(socket, conf)
        accept_loop(listen_socket, conf)

      {:error, :closed} ->
        exit(:normal)

      {:error, reason} when reason in [:emfile, :enfile, :system_limit] ->
        # out of file descriptors: wait a little instead of spinning
        Logger.warning("the web server cannot accept a connection: #{inspect(reason)}")
        Process.sleep(100)
        accept_loop(listen_socket, conf)

      {:error, _transient} ->
        accept_loop(listen_socket, conf)
    end
  end

  # Admission (Vws.Ops.Web.Clients): the connection's process is started only if its client
  # (peer address) and the server have room, made by closing idle connections if need be.
  defp hand_over(socket, conf) do
    start = fn ->
      Task.Supervisor.start_child(
        conf.connections,
        fn ->
          receive do
            {:socket, s, pace, idle_key} ->
              Clients.adopt(idle_key)
              Vws.Ops.Web.Conn.serve(s, pace, conf)
          end
        end,
        shutdown: :brutal_kill
      )
    end

    with {:ok, %{addr: ip}} when is_tuple(ip) <- :socket.peername(socket),
         {:ok, pid, pace, idle_key} <- Clients.admit(conf.clients, Clients.client(ip), start) do
      # (the socket is closed when its controlling process ends, as a port with its owner)
      case :socket.setopt(socket, {:otp, :controlling_process}, pid) do
        :ok -> send(pid, {:socket, socket, pace, idle_key})
        {:error, _} -> Process.exit(pid, :kill) && :socket.close(socket)
      end
    else
      {:refuse, :client} ->
        Vws.Ops.Web.Conn.refuse_busy(socket, "busy: too many connections from your address", conf)

      {:refuse, :rate} ->
        Vws.Ops.Web.Conn.refuse_busy(
          socket,
          "busy: too many new connections from your address",
          conf
        )

      {:refuse, :full} ->
        Vws.Ops.Web.Conn.refuse_busy(socket, "busy: too many connections", conf)

      _no_peer ->
        :socket.close(socket)
    end
  end
end
