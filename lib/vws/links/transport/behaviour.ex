defmodule Vws.Links.Transport.Behaviour do
  @moduledoc """
  What a transport implements: TCP (`Vws.Links.Transport.TCP`), a serial tty
  (`Vws.Links.Transport.Serial`), a terminal server's port over RFC 2217
  (`Vws.Links.Transport.RFC2217`), an in-memory loopback (`Vws.Links.Transport.Loopback`), a
  cluster's workstation (`Vws.CEC.Cell.Connection`).

  Protocol code calls the facade, `Vws.Links.Transport`, never a transport; the facade picks the
  transport from the endpoint. This module holds only the callbacks and their types, and depends
  on nothing, so a transport compiles against it without recompiling when the facade changes.

  The callbacks are named like the facade's functions and take the transport's own `handle`
  instead of a `Vws.Links.Transport.Conn`. A transport returns its errors as `{:error, reason}`
  with the `:inet`-style atoms where one fits (`:closed`, `:timeout`, `:econnrefused`,
  `:eaddrinuse`, `:not_owner`); the facade hands every one of them to its caller as
  `{:error, %Vws.Links.Transport.Error{reason: reason}}` (see there for every reason).

  Received bytes are delivered on demand (see `Vws.Links.Transport`): nothing reaches the
  controlling process until `activate/1`, then the next chunk (or the close) does — and, where
  the transport arms a few deliveries at a time (TCP, eight), a bounded number more. An owner
  whose bound is one delivery calls `activate_once/1` instead.
  """

  @typedoc "A transport's own value for one connection."
  @type handle :: term()
  @typedoc "A transport's own value for one listener."
  @type listener_handle :: term()
  @typedoc "Where to connect or listen, parsed (`Vws.Links.Endpoint`)."
  @type endpoint :: Vws.Links.Endpoint.t()
  @typedoc "What a message to the controlling process meant for the connection."
  @type message_result :: {:data, binary()} | :closed | {:error, term()} | :unknown

  @doc "Opens a connection to `endpoint`; the caller becomes its controlling process."
  @callback connect(endpoint(), keyword()) :: {:ok, handle()} | {:error, term()}

  @doc "Starts listening on `endpoint`; `{:error, :not_listenable}` if it cannot."
  @callback listen(endpoint(), keyword()) :: {:ok, listener_handle()} | {:error, term()}

  @doc "The bound endpoint of a listener."
  @callback listener_endpoint(listener_handle()) :: endpoint()

  @doc "Waits for the next incoming connection; the caller becomes its controlling process."
  @callback accept(listener_handle(), timeout()) :: {:ok, handle()} | {:error, term()}

  @doc "Stops listening; pending, not yet accepted connections are closed."
  @callback close_listener(listener_handle()) :: :ok

  @doc "Sends bytes."
  @callback send(handle(), iodata()) :: :ok | {:error, term()}

  @doc "Closes the connection; the peer sees it closed once it has received everything sent before."
  @callback close(handle()) :: :ok

  @doc "Makes `pid` the controlling process. Only the current controlling process may do it."
  @callback controlling_process(handle(), pid()) :: :ok | {:error, term()}

  @doc "Arms delivery of the next chunk of received bytes (or of the close) to the owner."
  @callback activate(handle()) :: :ok

  @doc """
  Arms delivery of the next chunk alone (the same as `activate/1` where that arms one; TCP's
  arms eight).
  """
  @callback activate_once(handle()) :: :ok

  @doc "Classifies a message received by the controlling process."
  @callback handle_message(handle(), term()) :: message_result()

  @doc "A printable description of the other end."
  @callback peer(handle()) :: String.t()
end
