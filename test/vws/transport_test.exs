defmodule Vws.TransportTest do
  use ExUnit.Case, async: true

  alias Vws.Endpoint
  alias Vws.Transport

  doctest Vws.Transport

  test "the endpoint picks the transport" do
    assert Transport.module_for(Endpoint.parse!("tcp://h:1")) == Vws.Transport.TCP
    assert Transport.module_for(Endpoint.parse!("tty:/dev/ttyS0")) == Vws.Transport.Serial
    assert Transport.module_for(Endpoint.parse!("loopback:x")) == Vws.Transport.Loopback
  end

  test "a bad endpoint string is returned as the parser's error" do
    assert {:error, %Endpoint.Error{reason: :bad_port}} = Transport.connect("tcp://h:x")
    assert {:error, %Endpoint.Error{reason: :unknown_scheme}} = Transport.listen("serial:0")
  end

  test "a tty cannot listen" do
    assert Transport.listen("tty:/dev/ttyS0") ==
             {:error, %Vws.Transport.Error{reason: :not_listenable}}
  end

  test "every transport implements the whole behaviour" do
    callbacks = Transport.behaviour_info(:callbacks)

    for module <- [Vws.Transport.TCP, Vws.Transport.Loopback, Vws.Transport.Serial] do
      Code.ensure_loaded!(module)

      behaviours = module.module_info(:attributes) |> Keyword.get_values(:behaviour)
      assert Transport in List.flatten(behaviours)

      for {name, arity} <- callbacks, do: assert(function_exported?(module, name, arity))
    end
  end
end
