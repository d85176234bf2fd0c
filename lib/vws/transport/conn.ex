defmodule Vws.Transport.Conn do
  @moduledoc """
  An open connection, as returned by `Vws.Transport.connect/2` and `Vws.Transport.accept/2`.

  `module` is the transport (`Vws.Transport.TCP`, `Vws.Transport.Serial`,
  `Vws.Transport.Loopback`), `handle` its own value for the connection (opaque to callers), and
  `endpoint` the endpoint the connection was made through: the one dialled for `connect/2`, the
  listener's bound endpoint for `accept/2`. Use `Vws.Transport.peer/1` for the other side.
  """

  @enforce_keys [:module, :handle, :endpoint]
  defstruct [:module, :handle, :endpoint]

  @type t :: %__MODULE__{module: module(), handle: term(), endpoint: Vws.Endpoint.t()}
end
