defmodule Vws.Links.Transport do
  @moduledoc """
  Byte links to equipment — TCP, a serial tty, or an in-memory loopback — behind one API.

  A `cell:<id>` endpoint names a workstation, not a place: it is resolved above this layer
  (`Vws.CEC.Cell.connect/2`), which passes the transport that reaches the workstation as the
  `transport:` option of `connect/2`. Without one, connecting to it is `{:error, :not_resolved}`.

  This module is the facade protocol code calls; every transport implements
  `Vws.Links.Transport.Behaviour`. The facade picks the transport from the endpoint
  (`Vws.Links.Endpoint`), so a driver written once runs unchanged over a real serial line, a
  terminal server, a simulator on TCP, or a loopback pair in tests.

  ## Receiving: on demand

  Received bytes are delivered as messages to the connection's *controlling process* (the process
  that connected or accepted, until `controlling_process/2` hands it on). Nothing is delivered
  until the owner calls `activate/1`; then the next chunk arrives as one message. The owner calls
  `activate/1` again after each. TCP arms eight deliveries at a time (`Vws.Links.Transport.TCP`:
  re-arming for each was a tenth of a VWS_STATUS poll's CPU), and says when they are used up with
  a chunk of no bytes; the others arm one. Either way what waits unread is bounded. An owner whose
  bound is one delivery — a simulated line that holds back its sender while its queue is full —
  calls `activate_once/1`. The owner passes every message it does not recognise to
  `handle_message/2`, which says whether it was data, the end of the connection, an error, or
  not this connection's at all:

      def handle_info(msg, state) do
        case Vws.Links.Transport.handle_message(state.conn, msg) do
          {:data, bytes} -> Vws.Links.Transport.activate(state.conn); decode(bytes, state)
          :closed -> link_down(state)
          {:error, reason} -> link_down(reason, state)
          :unknown -> unexpected(msg, state)
        end
      end

  The serial transport cannot hold bytes back (an Erlang port has no flow control), so it is
  always active and `activate/1` does nothing there; code written for active-once works unchanged.

  ## Example

      iex> {:ok, listener} = Vws.Links.Transport.listen("loopback:transport-doc")
      iex> {:ok, client} = Vws.Links.Transport.connect("loopback:transport-doc")
      iex> {:ok, server} = Vws.Links.Transport.accept(listener, 1000)
      iex> Vws.Links.Transport.send(client, ["ENQ", 5])
      :ok
      iex> Vws.Links.Transport.activate(server)
      :ok
      iex> receive do msg -> Vws.Links.Transport.handle_message(server, msg) end
      {:data, <<"ENQ", 5>>}
      iex> Vws.Links.Transport.close(client)
      :ok
      iex> Vws.Links.Transport.activate(server)
      :ok
      iex> receive do msg -> Vws.Links.Transport.handle_message(server, msg) end
      :closed
      iex> Vws.Links.Transport.close_listener(listener)
      :ok

  ## Errors

  Every failure is `{:error, %Vws.Links.Transport.Error{reason: reason}}` (see there for every
  reason); implementing a transport: `Vws.Links.Transport.Behaviour`.
  """

  import Kernel, except: [send: 2]
  require Logger

  alias Vws.Links.Endpoint
  alias Vws.Links.Transport.{Conn, Error, Listener}

  @typedoc "An endpoint, or its string form."
  @type endpoint :: Endpoint.t() | String.t()
  @typedoc "What the facade returns when a transport fails (`Vws.Links.Transport.Error`)."
  @type error :: {:error, Error.t() | Vws.Links.Endpoint.Error.t()}

  @doc """
  Connects to `endpoint` (a `Vws.Links.Endpoint` or its string form).

  TCP dials `host:port` (option `timeout`, default 5000 ms); tty opens the device; loopback
  connects to the listener registered under the name. The caller becomes the controlling process
  and must `activate/1` to receive. `transport:` names the transport module to use instead of
  the endpoint's own (how a `cell:` endpoint, resolved above this layer, is connected).
  """
  @spec connect(endpoint(), keyword()) :: {:ok, Conn.t()} | error()
  def connect(endpoint, opts \\ []) do
    {module, opts} = Keyword.pop(opts, :transport)

    with {:ok, endpoint} <- to_endpoint(endpoint),
         {:ok, module} <- connecting_module(module, endpoint) do
      with {:ok, handle} <- module.connect(endpoint, opts) do
        {:ok, %Conn{module: module, handle: handle, endpoint: endpoint}}
      end
    end
    |> Error.wrap()
  end

  @doc """
  Listens on `endpoint`.

  TCP listens with `reuseaddr` (option `ip` overrides the address taken from the endpoint; port 0
  picks a free port, see `listener_endpoint/1`); loopback registers the name in `Vws.Registry`
  (`{:error, :eaddrinuse}` if taken). A tty cannot listen: `{:error, :not_listenable}`. The
  listener is closed when the calling process exits.
  """
  @spec listen(endpoint(), keyword()) :: {:ok, Listener.t()} | error()
  def listen(endpoint, opts \\ []) do
    with {:ok, endpoint} <- to_endpoint(endpoint),
         {:ok, module} <- listening_module(endpoint) do
      with {:ok, handle} <- module.listen(endpoint, opts) do
        {:ok,
         %Listener{module: module, handle: handle, endpoint: module.listener_endpoint(handle)}}
      end
    end
    |> Error.wrap()
  end

  @doc "The endpoint a listener is bound to, with the real port when port 0 was asked for."
  @spec listener_endpoint(Listener.t()) :: Endpoint.t()
  def listener_endpoint(%Listener{endpoint: endpoint}), do: endpoint

  @doc """
  Waits up to `timeout` for a connection on `listener` (blocking: run it in an acceptor process).

  The caller becomes the controlling process of the returned connection; hand it on with
  `controlling_process/2`.
  """
  @spec accept(Listener.t(), timeout()) :: {:ok, Conn.t()} | error()
  def accept(%Listener{module: module, handle: handle, endpoint: endpoint}, timeout) do
    with {:ok, conn_handle} <- module.accept(handle, timeout) do
      {:ok, %Conn{module: module, handle: conn_handle, endpoint: endpoint}}
    end
    |> Error.wrap()
  end

  @doc """
  Starts a process, linked to the caller, that accepts connections on `listener` for ever: each
  one is handed to `owner` (its controlling process from then on) as the message `{tag, conn}`.
  When accepting fails (the listener was closed) it exits `{:shutdown, {:accept_failed, reason}}`.

  Option `allow` (`Vws.Links.Transport.Policy`; default `:loopback`): a connection from an address not
  on it is closed before `owner` hears of it, logged (at most one line a second, with a count)
  and counted as the telemetry event `[:vws, :transport, :refused]` (metadata `peer`,
  `listener`). Connections without an address (loopback pairs, ttys) are always handed on.
  """
  @spec start_acceptor(Listener.t(), pid, atom, keyword) :: pid
  def start_acceptor(%Listener{} = listener, owner, tag, opts \\ []) do
    allow = Keyword.get(opts, :allow, :loopback)
    spawn_link(fn -> accept_loop(listener, owner, tag, allow, {nil, 0}) end)
  end

  defp accept_loop(listener, owner, tag, allow, refusals) do
    case accept(listener, :infinity) do
      {:ok, conn} ->
        case peer_address(conn) do
          {:ok, ip} ->
            if Vws.Links.Transport.Policy.allowed?(allow, ip) do
              hand_on(conn, owner, tag)
              accept_loop(listener, owner, tag, allow, refusals)
            else
              refusals = refuse(listener, conn, allow, refusals)
              accept_loop(listener, owner, tag, allow, refusals)
            end

          :none ->
            hand_on(conn, owner, tag)
            accept_loop(listener, owner, tag, allow, refusals)

          {:error, _gone} ->
            close(conn)
            accept_loop(listener, owner, tag, allow, refusals)
        end

      {:error, reason} ->
        exit({:shutdown, {:accept_failed, reason}})
    end
  end

  defp hand_on(conn, owner, tag) do
    :ok = controlling_process(conn, owner)
    Kernel.send(owner, {tag, conn})
  end

  # One log line a second at most: the first refusal at once, later ones counted into the next.
  defp refuse(listener, conn, allow, {last, suppressed}) do
    peer = peer(conn)

    Vws.Telemetry.execute([:vws, :transport, :refused], %{count: 1}, %{
      peer: peer,
      listener: to_string(listener.endpoint)
    })

    now = System.monotonic_time(:millisecond)

    if last == nil or now - last >= 1_000 do
      more = if suppressed > 0, do: " (and #{suppressed} more since the last such line)", else: ""

      Logger.warning(
        "refused a connection from #{peer} to #{listener.endpoint}: not allowed " <>
          "(#{Vws.Links.Transport.Policy.describe(allow)})#{more}"
      )

      close(conn)
      {now, 0}
    else
      close(conn)
      {last, suppressed + 1}
    end
  end

  @doc """
  The other end's IP address, `{:ok, ip}`, for transports that have one (TCP); `:none` for the
  others (tty, loopback pairs), and for a TCP connection already closed (`{:error, reason}`).
  """
  @spec peer_address(Conn.t()) :: {:ok, :inet.ip_address()} | :none | {:error, term}
  def peer_address(%Conn{module: Vws.Links.Transport.TCP, handle: socket}) do
    case :inet.peername(socket) do
      {:ok, {ip, _port}} -> {:ok, ip}
      {:error, reason} -> {:error, reason}
    end
  end

  def peer_address(%Conn{}), do: :none

  @doc "Stops listening."
  @spec close_listener(Listener.t()) :: :ok
  def close_listener(%Listener{module: module, handle: handle}), do: module.close_listener(handle)

  @doc "Sends `data`; blocks while the peer is far behind (TCP and loopback)."
  @spec send(Conn.t(), iodata()) :: :ok | error()
  def send(%Conn{module: module, handle: handle}, data),
    do: module.send(handle, data) |> Error.wrap()

  @doc "Closes the connection. Always `:ok`, also when it was already closed."
  @spec close(Conn.t()) :: :ok
  def close(%Conn{module: module, handle: handle}), do: module.close(handle)

  @doc "Hands the connection to `pid`; must be called by the current controlling process."
  @spec controlling_process(Conn.t(), pid()) :: :ok | error()
  def controlling_process(%Conn{module: module, handle: handle}, pid),
    do: module.controlling_process(handle, pid) |> Error.wrap()

  @doc """
  Arms delivery of the next chunk of received bytes (or of the close) to the controlling process.

  Always `:ok`: on a connection that is already closed it does nothing, the close having been
  reported (or being reported) through `handle_message/2`. A no-op on the serial transport,
  which is always active.
  """
  @spec activate(Conn.t()) :: :ok
  def activate(%Conn{module: module, handle: handle}), do: module.activate(handle)

  @doc """
  Arms delivery of the next chunk alone (`activate/1` may arm a few, as TCP does): for an owner
  that must hold its sender back after every chunk (`Vws.Sim.Line`'s pumps, whose queue is
  bounded). Always `:ok`, as `activate/1`.
  """
  @spec activate_once(Conn.t()) :: :ok
  def activate_once(%Conn{module: module, handle: handle}), do: module.activate_once(handle)

  @doc """
  Classifies `msg`, received by the controlling process: `{:data, bytes}`, `:closed`,
  `{:error, reason}` (the connection is unusable after it), or `:unknown` when the message does
  not belong to this connection.
  """
  @spec handle_message(Conn.t(), term()) ::
          {:data, binary()} | :closed | {:error, Error.t()} | :unknown
  def handle_message(%Conn{module: module, handle: handle}, msg),
    do: module.handle_message(handle, msg) |> Error.wrap()

  @doc "A printable description of the other end, for logs."
  @spec peer(Conn.t()) :: String.t()
  def peer(%Conn{module: module, handle: handle}), do: module.peer(handle)

  @doc """
  The transport module serving an endpoint (`rfc2217:` — `Vws.Links.Transport.RFC2217`); nil for a
  `cell:` endpoint (resolved above).
  """
  @spec module_for(Endpoint.t()) :: module() | nil
  def module_for(%Endpoint{kind: :tcp}), do: Vws.Links.Transport.TCP
  def module_for(%Endpoint{kind: :tty}), do: Vws.Links.Transport.Serial
  def module_for(%Endpoint{kind: :rfc2217}), do: Vws.Links.Transport.RFC2217
  def module_for(%Endpoint{kind: :loopback}), do: Vws.Links.Transport.Loopback
  def module_for(%Endpoint{kind: :cell}), do: nil

  defp connecting_module(nil, endpoint) do
    case module_for(endpoint) do
      nil -> {:error, :not_resolved}
      module -> {:ok, module}
    end
  end

  defp connecting_module(module, _endpoint) when is_atom(module), do: {:ok, module}

  defp listening_module(endpoint) do
    case module_for(endpoint) do
      nil -> {:error, :not_listenable}
      module -> {:ok, module}
    end
  end

  defp to_endpoint(%Endpoint{} = endpoint), do: {:ok, endpoint}
  defp to_endpoint(string), do: Endpoint.parse(string)
end
