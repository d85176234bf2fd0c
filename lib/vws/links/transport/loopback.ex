defmodule Vws.Links.Transport.Loopback do
  @moduledoc """
  `Vws.Links.Transport` as an in-memory pair inside one node: no sockets, no OS resources.

  Tests and simulators plug links together with it (`loopback:dnc`). A listener registers its name
  in `Vws.Registry` under `{:loopback, name}`; each connection is one small process holding both
  directions, so thousands of pairs cost thousands of processes and nothing else.

  Semantics follow TCP: a `connect/2` succeeds as soon as a listener exists (up to `backlog`
  unaccepted connections, option of `listen/2`, default 128) and `accept/2` picks connections up
  in order; bytes arrive in order and none are lost; received bytes are held until the owner
  calls `activate/1`, then everything held arrives as one message
  `{:vws_loopback, ref, binary}`; when one side closes or its controlling process exits, the
  other side receives the remaining bytes and then `{:vws_loopback_closed, ref}`. A `send/2`
  blocks while the peer holds more than 1 MB it has not taken (back-pressure), so a sender
  cannot grow a buffer without bound.

  The handle is this module's struct; `ref` tags the messages of one side.
  """

  @behaviour Vws.Links.Transport.Behaviour

  import Kernel, except: [send: 2]

  alias Vws.Links.Endpoint
  alias Vws.Links.Transport.Loopback.{Listener, Pair}

  @enforce_keys [:pair, :side, :ref, :name]
  defstruct [:pair, :side, :ref, :name]

  @type t :: %__MODULE__{pair: pid(), side: :client | :server, ref: reference(), name: term()}

  @connect_timeout 5000
  @backlog 128

  @impl true
  def connect(%Endpoint{kind: :loopback, name: name}, opts) do
    case Listener.whereis(name) do
      nil ->
        {:error, :econnrefused}

      listener ->
        try do
          GenServer.call(
            listener,
            {:connect, self()},
            Keyword.get(opts, :timeout, @connect_timeout)
          )
        catch
          :exit, {:timeout, _} -> {:error, :timeout}
          :exit, _ -> {:error, :econnrefused}
        end
    end
  end

  @doc """
  Connects to the loopback listener `listener` (a pid, which may run on another node of the
  cell) registered as `name`, as `connect/2` does, except that the connection's process runs on
  the caller's node and watches the listener and, once accepted, the acceptor: if their node
  goes away (or they exit) the caller receives the close, as from any peer that closed. Used by
  `Vws.CEC.Cell.Connection` to carry a WC link over Erlang distribution.
  """
  @spec connect_listener(pid(), term(), keyword()) :: {:ok, t()} | {:error, term()}
  def connect_listener(listener, name, opts \\ []) when is_pid(listener) do
    client_ref = make_ref()
    server_ref = make_ref()
    {:ok, pair} = Pair.start(name, self(), listener, client_ref, server_ref)
    server = %__MODULE__{pair: pair, side: :server, ref: server_ref, name: name}

    result =
      try do
        GenServer.call(
          listener,
          {:connect_pair, server},
          Keyword.get(opts, :timeout, @connect_timeout)
        )
      catch
        :exit, {:timeout, _} -> {:error, :timeout}
        :exit, _ -> {:error, :econnrefused}
      end

    case result do
      :ok ->
        {:ok, %__MODULE__{pair: pair, side: :client, ref: client_ref, name: name}}

      {:error, _} = error ->
        Pair.close(pair, :server)
        Pair.close(pair, :client)
        error
    end
  end

  @impl true
  def listen(%Endpoint{kind: :loopback, name: name} = endpoint, opts) do
    with {:ok, pid} <- Listener.start(name, self(), Keyword.get(opts, :backlog, @backlog)) do
      {:ok, {pid, endpoint}}
    end
  end

  @impl true
  def listener_endpoint({_pid, endpoint}), do: endpoint

  @impl true
  def accept({pid, _endpoint}, timeout) do
    GenServer.call(pid, {:accept, timeout}, :infinity)
  catch
    :exit, _ -> {:error, :closed}
  end

  @impl true
  def close_listener({pid, _endpoint}) do
    GenServer.call(pid, :close, :infinity)
  catch
    :exit, _ -> :ok
  end

  @impl true
  def send(%__MODULE__{pair: pair, side: side}, data),
    do: Pair.send(pair, side, IO.iodata_to_binary(data))

  @impl true
  def close(%__MODULE__{pair: pair, side: side}), do: Pair.close(pair, side)

  @impl true
  def controlling_process(%__MODULE__{pair: pair, side: side}, pid),
    do: Pair.controlling_process(pair, side, pid)

  @impl true
  def activate(%__MODULE__{pair: pair, side: side}), do: Pair.activate(pair, side)

  # (activate/1 arms one delivery already)
  @impl true
  def activate_once(conn), do: activate(conn)

  @impl true
  def handle_message(%__MODULE__{ref: ref}, {:vws_loopback, ref, data}), do: {:data, data}
  def handle_message(%__MODULE__{ref: ref}, {:vws_loopback_closed, ref}), do: :closed
  def handle_message(%__MODULE__{}, _msg), do: :unknown

  @impl true
  def peer(%__MODULE__{side: side, name: name}) do
    other = if side == :client, do: "server", else: "client"
    "#{Endpoint.to_string(%Endpoint{kind: :loopback, name: name})} (#{other})"
  end
end
