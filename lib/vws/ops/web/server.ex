defmodule Vws.Ops.Web.Server do
  @moduledoc """
  A small, bounded HTTP/1.1 server on `:gen_tcp` — the listener of `Vws.Ops.Web`.

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
    * at most `:max_connections` open connections [1024]; one more is answered 503 at once and
      closed (it never waits in a queue);
    * at most `:max_requests` requests per kept-alive connection [100]; an answer that the client
      does not read within `:send_timeout` ms [10 000] closes the connection;
    * at most `:max_rate` requests a second are served, all connections together [500; the
      dashboard asks 2.5 a second per open page]: a request beyond it waits its turn (the client
      is held, not sent away to come straight back), and one that would wait more than 10 s is
      answered 503. HTTP load is so bounded in CPU and
      socket work whatever the number of clients, which is what keeps the WC's answers on time
      (`bench/http_load.exs`).

  Each connection is a process of its own (under a `Task.Supervisor` whose `max_children` is the
  connection limit) reading passively with timeouts from a raw socket; the head is parsed line by
  line by OTP's HTTP parser (`:erlang.decode_packet/3`, the one of `packet: :http_bin`) from a
  buffer that never holds more than `:max_line` bytes and one read of the socket, and the bytes
  after it — a body, or the next request of a client that pipelines — are kept for what follows
  (`Vws.Ops.Web.Conn`). Acceptors and connections run at low process priority, so the
  workstations' own processes — SUN_COMM answering its WC first of all — are scheduled before any
  HTTP work (`bench/http_load.exs` measures it).
  """
  use GenServer
  require Logger

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
    max_requests: 100,
    send_timeout: 10_000,
    max_rate: 500
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

  @doc "The dashboard's URL."
  @spec url(pid) :: String.t()
  def url(server), do: GenServer.call(server, :url)

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    bind = Keyword.get(opts, :bind, "127.0.0.1")

    with {:ok, address} <- parse_address(bind),
         limits = Keyword.merge(@defaults, Keyword.take(opts, Keyword.keys(@defaults))),
         {:ok, socket} <- listen(address, Keyword.get(opts, :port, 4000), limits) do
      {:ok, port} = :inet.port(socket)
      url = "http://#{host(bind)}:#{port}/"

      settings = %{
        agent: Keyword.fetch!(opts, :agent),
        snapshot: Keyword.fetch!(opts, :snapshot),
        token: blank_to_nil(opts[:token]),
        read_token: blank_to_nil(opts[:read_token]),
        port: port
      }

      conf = %{
        settings: settings,
        limits: Map.new(limits),
        connections: Keyword.fetch!(opts, :connections),
        # the time (µs, monotonic) from which the next request may be served: see pace/1
        pace: pace_counter()
      }

      acceptors = for _ <- 1..@acceptors, do: spawn_link(fn -> accept_loop(socket, conf) end)

      Logger.info(
        "VWS web server on #{url} (#{mode(settings)}; at most #{limits[:max_connections]} connections)"
      )

      {:ok, %{socket: socket, port: port, url: url, acceptors: acceptors}}
    else
      {:error, reason} -> {:stop, {:cannot_listen, bind, opts[:port], reason}}
    end
  end

  # monotonic time may be negative: the counter starts at now, not 0
  defp pace_counter do
    ref = :atomics.new(1, signed: true)
    :atomics.put(ref, 1, System.monotonic_time(:microsecond))
    ref
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

  defp listen(address, port, limits) do
    :gen_tcp.listen(port, [
      :binary,
      if(tuple_size(address) == 8, do: :inet6, else: :inet),
      ip: address,
      packet: :raw,
      active: false,
      reuseaddr: true,
      nodelay: true,
      backlog: 1024,
      send_timeout: limits[:send_timeout],
      send_timeout_close: true
    ])
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

  @impl true
  def handle_info({:EXIT, pid, reason}, s) do
    if pid in s.acceptors,
      do: {:stop, {:acceptor_down, reason}, s},
      else: {:noreply, s}
  end

  def handle_info(_msg, s), do: {:noreply, s}

  @impl true
  def terminate(_reason, %{socket: socket}) do
    :gen_tcp.close(socket)
    :ok
  end

  ## Acceptors

  defp accept_loop(listen_socket, conf) do
    Process.flag(:priority, :low)

    case :gen_tcp.accept(listen_socket) do
      {:ok, socket} ->
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

  defp hand_over(socket, conf) do
    case Task.Supervisor.start_child(
           conf.connections,
           fn -> receive(do: ({:socket, s} -> Vws.Ops.Web.Conn.serve(s, conf))) end,
           shutdown: :brutal_kill
         ) do
      {:ok, pid} ->
        case :gen_tcp.controlling_process(socket, pid) do
          :ok -> send(pid, {:socket, socket})
          {:error, _} -> Process.exit(pid, :kill) && :gen_tcp.close(socket)
        end

      {:error, :max_children} ->
        Vws.Ops.Web.Conn.refuse_busy(socket, conf)

      {:error, _} ->
        :gen_tcp.close(socket)
    end
  end
end
