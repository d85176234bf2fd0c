defmodule Vws.Links.Transport.ErrorTest do
  use ExUnit.Case, async: true

  alias Vws.Links.Transport
  alias Vws.Links.Transport.Error

  doctest Error

  test "every error of the facade is one struct, whatever the transport" do
    assert {:error, %Error{reason: :econnrefused} = e} =
             Transport.connect("loopback:transport-error-none")

    assert Exception.message(e) =~ "connection refused"
    assert {:error, %Error{reason: :not_listenable}} = Transport.listen("tty:/dev/ttyS0")
    assert {:error, %Error{reason: :not_resolved}} = Transport.connect("cell:x")
    # an endpoint that cannot be read is the endpoint's own error
    assert {:error, %Vws.Links.Endpoint.Error{reason: :unknown_scheme}} =
             Transport.connect("ftp://x")
  end

  test "every reason reads in words" do
    for reason <- [
          :closed,
          :timeout,
          :econnrefused,
          :eaddrinuse,
          :not_owner,
          :not_listenable,
          :not_resolved,
          :not_found,
          :not_listening,
          :not_reachable,
          :enoent,
          :eacces,
          :not_a_tty,
          :socat_not_found,
          {:socat_exit, 1},
          {:unknown_backend, :x},
          :econnreset,
          "cannot resolve the address"
        ] do
      text = Exception.message(%Error{reason: reason})
      refute text =~ "%", inspect(reason)
      refute text =~ "transport error", inspect(reason)
    end

    assert Exception.message(%Error{reason: {:weird, 1}}) == "transport error {:weird, 1}"
  end
end
