defmodule Vws.Links.TransportTest do
  use ExUnit.Case, async: true

  alias Vws.Links.Endpoint
  alias Vws.Links.Transport

  doctest Vws.Links.Transport

  test "the endpoint picks the transport" do
    assert Transport.module_for(Endpoint.parse!("tcp://h:1")) == Vws.Links.Transport.TCP
    assert Transport.module_for(Endpoint.parse!("tty:/dev/ttyS0")) == Vws.Links.Transport.Serial
    assert Transport.module_for(Endpoint.parse!("loopback:x")) == Vws.Links.Transport.Loopback
  end

  test "a bad endpoint string is returned as the parser's error" do
    assert {:error, %Endpoint.Error{reason: :bad_port}} = Transport.connect("tcp://h:x")
    assert {:error, %Endpoint.Error{reason: :unknown_scheme}} = Transport.listen("serial:0")
  end

  test "a tty cannot listen" do
    assert Transport.listen("tty:/dev/ttyS0") ==
             {:error, %Vws.Links.Transport.Error{reason: :not_listenable}}
  end

  test "every transport implements the whole behaviour, and the facade offers each callback" do
    callbacks = Transport.Behaviour.behaviour_info(:callbacks)
    assert {:handle_message, 2} in callbacks

    for module <- [
          Vws.Links.Transport.TCP,
          Vws.Links.Transport.Loopback,
          Vws.Links.Transport.Serial
        ] do
      Code.ensure_loaded!(module)

      behaviours = module.module_info(:attributes) |> Keyword.get_values(:behaviour)
      assert Transport.Behaviour in List.flatten(behaviours)

      for {name, arity} <- callbacks, do: assert(function_exported?(module, name, arity))
    end

    for {name, arity} <- callbacks, do: assert(function_exported?(Transport, name, arity))
  end
end
