defmodule Vws.Sim.Tap do
  @moduledoc """
  A transport that wraps another and taps its bytes: a simulator's misbehaving line end, put
  under a product link without the link knowing (`Vws.Sim.GE2000`'s faults under its
  `Vws.Links.DNC` link). The link sends and receives through the wrapped connection as through
  any `Vws.Links.Transport`; each frame it sends and each chunk it receives passes a **tap
  module** first, which may change, drop or add bytes.

  The tap is a process (`start_link/1`) holding the tap module and its state, so that the
  simulator can change it at run time (`set/2`) while the link owns the connection. Wrap an
  accepted connection with `wrap/2` before handing it to the link, or let the link dial through
  the tap with the connect options `[transport: Vws.Sim.Tap, tap: tap]`.

  A tap module implements:

    * `outgoing(state, bytes) :: {state, iodata}` — one send of the link (a DNC link sends one
      frame or control a call); `[]` sends nothing;
    * `incoming(state, bytes) :: {state, bytes, [term]}` — one received chunk; the list holds
      notes for the tap's owner, sent to it as `{:tap, tap, note}` (a simulator that must act,
      as the GE-2000 bidding against the CEC);
    * `describe(state) :: term` (optional) — the fault, for `describe/1`.

      iex> {:ok, listener} = Vws.Links.Transport.listen("loopback:tap-doc")
      iex> {:ok, tap} = Vws.Sim.Tap.start_link(owner: self())
      iex> {:ok, client} = Vws.Links.Transport.connect("loopback:tap-doc", transport: Vws.Sim.Tap, tap: tap)
      iex> {:ok, server} = Vws.Links.Transport.accept(listener, 1000)
      iex> :ok = Vws.Sim.Tap.set(tap, {Vws.Sim.GE2000.Faults, Vws.Sim.GE2000.Faults.new(:silent)})
      iex> Vws.Sim.Tap.describe(tap)
      :silent
      iex> :ok = Vws.Links.Transport.send(client, <<0x05>>)
      iex> :ok = Vws.Sim.Tap.set(tap, nil)
      iex> :ok = Vws.Links.Transport.send(client, <<0x04>>)
      iex> :ok = Vws.Links.Transport.activate(server)
      iex> receive do msg -> Vws.Links.Transport.handle_message(server, msg) end
      {:data, <<0x04>>}
  """

  @behaviour Vws.Links.Transport.Behaviour

  use GenServer

  import Kernel, except: [send: 2]

  alias Vws.Links.Transport
  alias Vws.Links.Transport.Conn

  @type tap :: GenServer.server()

  ## The tap process

  @doc """
  Starts a tap, linked to the caller, that lets everything through until `set/2`. Option
  `owner`: the pid told the tap module's notes (default: the caller).
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts \\ []) do
    opts = Vws.Options.validate!(opts, [owner: [type: :any, default: self()]], "tap")
    GenServer.start_link(__MODULE__, opts[:owner])
  end

  @doc "Puts `{module, state}` in the line, or takes the tap module out (`nil`)."
  @spec set(tap, {module, term} | nil) :: :ok
  def set(tap, module_state), do: GenServer.call(tap, {:set, module_state})

  @doc "What the tap does to the line: `module.describe(state)`, the module, or `:none`."
  @spec describe(tap) :: term
  def describe(tap), do: GenServer.call(tap, :describe)

  @doc "The connection `conn` (the caller's) with its bytes passing `tap`."
  @spec wrap(Conn.t(), tap) :: Conn.t()
  def wrap(%Conn{} = conn, tap),
    do: %Conn{module: __MODULE__, handle: {conn, tap}, endpoint: conn.endpoint}

  @impl GenServer
  def init(owner), do: {:ok, %{owner: owner, tap: nil}}

  @impl GenServer
  def handle_call({:set, tap}, _from, s), do: {:reply, :ok, %{s | tap: tap}}

  def handle_call(:describe, _from, %{tap: nil} = s), do: {:reply, :none, s}

  def handle_call(:describe, _from, %{tap: {mod, state}} = s) do
    Code.ensure_loaded(mod)
    {:reply, if(function_exported?(mod, :describe, 1), do: mod.describe(state), else: mod), s}
  end

  def handle_call({:outgoing, bytes}, _from, %{tap: nil} = s), do: {:reply, bytes, s}

  def handle_call({:outgoing, bytes}, _from, %{tap: {mod, state}} = s) do
    {state, out} = mod.outgoing(state, bytes)
    {:reply, out, %{s | tap: {mod, state}}}
  end

  def handle_call({:incoming, bytes}, _from, %{tap: nil} = s), do: {:reply, bytes, s}

  def handle_call({:incoming, bytes}, _from, %{tap: {mod, state}} = s) do
    {state, bytes, notes} = mod.incoming(state, bytes)
    for note <- notes, do: Kernel.send(s.owner, {:tap, self(), note})
    {:reply, bytes, %{s | tap: {mod, state}}}
  end

  ## The transport

  @impl true
  def connect(endpoint, opts) do
    {tap, opts} = Keyword.pop(opts, :tap)

    if tap == nil, do: raise(ArgumentError, "Vws.Sim.Tap.connect needs tap: a tap process")

    case Transport.connect(endpoint, opts) do
      {:ok, conn} -> {:ok, {conn, tap}}
      {:error, %{reason: reason}} -> {:error, reason}
    end
  end

  @impl true
  def listen(_endpoint, _opts), do: {:error, :not_listenable}

  @impl true
  def listener_endpoint(_listener), do: raise(ArgumentError, "a tap does not listen")

  @impl true
  def accept(_listener, _timeout), do: {:error, :not_listenable}

  @impl true
  def close_listener(_listener), do: :ok

  @impl true
  def send({conn, tap}, data) do
    case GenServer.call(tap, {:outgoing, IO.iodata_to_binary(data)}) do
      [] -> :ok
      "" -> :ok
      out -> unwrap(Transport.send(conn, out))
    end
  end

  @impl true
  def close({conn, _tap}), do: Transport.close(conn)

  @impl true
  def controlling_process({conn, _tap}, pid), do: unwrap(Transport.controlling_process(conn, pid))

  @impl true
  def activate({conn, _tap}), do: Transport.activate(conn)

  @impl true
  def activate_once({conn, _tap}), do: Transport.activate_once(conn)

  @impl true
  def handle_message({conn, tap}, message) do
    case Transport.handle_message(conn, message) do
      {:data, bytes} -> {:data, GenServer.call(tap, {:incoming, bytes})}
      {:error, %{reason: reason}} -> {:error, reason}
      other -> other
    end
  end

  @impl true
  def peer({conn, _tap}), do: Transport.peer(conn)

  defp unwrap({:error, %{reason: reason}}), do: {:error, reason}
  defp unwrap(other), do: other
end
