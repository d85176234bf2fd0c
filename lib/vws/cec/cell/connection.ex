defmodule Vws.CEC.Cell.Connection do
  @moduledoc """
  A connection to a `cell:<id>` endpoint: the WC link of workstation `id`, wherever it runs
  in the cell of connected nodes (`Vws.CEC.Cell`). A connection only: a cell endpoint cannot be
  listened on.

  `cell:` names a workstation, not a place, so it is resolved here, above the transports:
  `Vws.CEC.Cell.connect/2` hands this module to `Vws.Links.Transport.connect/2` as `transport:`, and the
  transports themselves know nothing of the cell. `connect/2` asks the cell where the workstation's SUN_COMM listens (`Vws.CEC.Cell.resolve/2`) and
  connects there:

    * a `loopback:` listener, local or on another node: through
      `Vws.Links.Transport.Loopback.connect_listener/3`. The connection's process runs on the caller's
      node, so the bytes SUN_COMM sends reach the caller as Erlang messages over distribution,
      and if the workstation's node goes away the caller receives the close;
    * a `tcp://` listener: a TCP connection (a listener bound to `0.0.0.0` on another node is
      dialled at that node's host);
    * a tty: `{:error, :not_reachable}` — the WC of that workstation is on its serial line.

  If the caller's node goes away instead, SUN_COMM's side learns nothing until the next WC
  connects and takes over — as when the far end of a serial line is unplugged.

  Every later call is passed to the transport of the connection made; the handle is this
  module's struct. The bytes are those of a direct connection: nothing is added or framed.

      iex> {:ok, _} = Vws.CEC.Workstation.start(id: "doc-cell-transport", wc: "loopback:doc-cell-transport")
      iex> {:ok, wc} = Vws.Peers.WC.Client.connect("cell:doc-cell-transport")
      iex> Vws.Peers.WC.Client.status(wc, "ROBOT_CMD")
      {:ok, "0000NONE"}
      iex> Vws.Peers.WC.Client.close(wc)
      iex> Vws.CEC.Workstation.stop("doc-cell-transport")
      :ok

  Errors of `connect/2`: `:not_found` (no node of the cell runs the workstation),
  `:not_listening` (its SUN_COMM is not listening yet: a client retries), `:not_reachable`, or
  those of the underlying transport.
  """

  @behaviour Vws.Links.Transport.Behaviour

  import Kernel, except: [send: 2]

  alias Vws.Links.Endpoint
  alias Vws.Links.Transport.Loopback

  @enforce_keys [:id, :node, :module, :handle]
  defstruct [:id, :node, :module, :handle]

  @type t :: %__MODULE__{id: term, node: node, module: module, handle: term}

  @impl true
  def connect(%Endpoint{kind: :cell, name: id}, opts) do
    timeout = Keyword.get(opts, :timeout, 5_000)

    with {:ok, node, listening} <- Vws.CEC.Cell.resolve(id, timeout),
         {:ok, module, handle} <- connect_to(node, listening, opts, timeout) do
      {:ok, %__MODULE__{id: id, node: node, module: module, handle: handle}}
    end
  end

  defp connect_to(node, %Endpoint{kind: :loopback, name: name}, opts, timeout) do
    listener =
      try do
        if node == node(),
          do: Loopback.Listener.whereis(name),
          else: :erpc.call(node, Loopback.Listener, :whereis, [name], timeout)
      catch
        _, _ -> nil
      end

    with pid when is_pid(pid) <- listener || {:error, :econnrefused},
         {:ok, handle} <- Loopback.connect_listener(pid, name, opts) do
      {:ok, Loopback, handle}
    end
  end

  defp connect_to(node, %Endpoint{kind: :tcp} = endpoint, opts, _timeout) do
    endpoint =
      if endpoint.host == ~c"0.0.0.0" and node != node(),
        do: %{endpoint | host: node |> Atom.to_charlist() |> Enum.drop_while(&(&1 != ?@)) |> tl()},
        else: endpoint

    with {:ok, handle} <- Vws.Links.Transport.TCP.connect(endpoint, opts) do
      {:ok, Vws.Links.Transport.TCP, handle}
    end
  end

  defp connect_to(_node, _endpoint, _opts, _timeout), do: {:error, :not_reachable}

  @impl true
  def listen(_endpoint, _opts), do: {:error, :not_listenable}

  @impl true
  def listener_endpoint(_listener), do: raise(ArgumentError, "a cell endpoint has no listener")

  @impl true
  def accept(_listener, _timeout), do: {:error, :not_listenable}

  @impl true
  def close_listener(_listener), do: :ok

  @impl true
  def send(%__MODULE__{module: m, handle: h}, data), do: m.send(h, data)

  @impl true
  def close(%__MODULE__{module: m, handle: h}), do: m.close(h)

  @impl true
  def controlling_process(%__MODULE__{module: m, handle: h}, pid),
    do: m.controlling_process(h, pid)

  @impl true
  def activate(%__MODULE__{module: m, handle: h}), do: m.activate(h)

  @impl true
  def activate_once(%__MODULE__{module: m, handle: h}), do: m.activate_once(h)

  @impl true
  def handle_message(%__MODULE__{module: m, handle: h}, msg), do: m.handle_message(h, msg)

  @impl true
  def peer(%__MODULE__{id: id, node: node, module: m, handle: h}),
    do: "cell:#{if is_binary(id), do: id, else: inspect(id)} on #{node} (#{m.peer(h)})"
end
