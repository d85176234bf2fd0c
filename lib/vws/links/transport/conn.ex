defmodule Vws.Links.Transport.Conn do
  @moduledoc """
  An open connection, as returned by `Vws.Links.Transport.connect/2` and `Vws.Links.Transport.accept/2`.

  `module` is the transport (`Vws.Links.Transport.TCP`, `Vws.Links.Transport.Serial`,
  `Vws.Links.Transport.Loopback`), `handle` its own value for the connection (opaque to callers), and
  `endpoint` the endpoint the connection was made through: the one dialled for `connect/2`, the
  listener's bound endpoint for `accept/2`. Use `Vws.Links.Transport.peer/1` for the other side.
  """

  @enforce_keys [:module, :handle, :endpoint]
  defstruct [:module, :handle, :endpoint]

  @type t :: %__MODULE__{module: module(), handle: term(), endpoint: Vws.Links.Endpoint.t()}
end
