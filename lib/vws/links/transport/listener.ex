defmodule Vws.Links.Transport.Listener do
  @moduledoc """
  A listening endpoint, as returned by `Vws.Links.Transport.listen/2`.

  `endpoint` is the bound endpoint (with the real port when port 0 was asked for); `handle` is the
  transport's own value (opaque to callers).
  """

  @enforce_keys [:module, :handle, :endpoint]
  defstruct [:module, :handle, :endpoint]

  @type t :: %__MODULE__{module: module(), handle: term(), endpoint: Vws.Links.Endpoint.t()}
end
