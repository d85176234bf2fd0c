defmodule Vws.Links.Transport.TCPTest do
  use ExUnit.Case, async: true
  use Vws.TransportConformance, listen_on: fn -> "tcp://127.0.0.1:0" end, armed: 8

  test "port 0 gives a real port, and the ip option binds the address", %{endpoint: endpoint} do
    assert %Vws.Links.Endpoint{kind: :tcp, host: ~c"127.0.0.1", port: port} = endpoint
    assert port > 0

    {:ok, listener} = Transport.listen("tcp://localhost:0", ip: {127, 0, 0, 1})
    assert %Vws.Links.Endpoint{host: ~c"127.0.0.1"} = Transport.listener_endpoint(listener)
    :ok = Transport.close_listener(listener)
  end

  test "the messages are the standard :gen_tcp ones", %{client: client, server: server} do
    :ok = Transport.send(client, "x")
    :ok = Transport.activate(server)
    assert_receive {:tcp, socket, "x"}, 5000
    assert socket == server.handle

    assert Transport.handle_message(server, {:tcp_error, socket, :etimedout}) ==
             {:error, %Vws.Links.Transport.Error{reason: :etimedout}}
  end

  test "peer names the remote address", %{client: client, endpoint: endpoint} do
    assert Transport.peer(client) == "tcp://127.0.0.1:#{endpoint.port}"
  end

  test "connect to a port nobody listens on is refused", %{listener: listener, endpoint: endpoint} do
    :ok = Transport.close_listener(listener)

    assert Transport.connect(endpoint, timeout: 1000) ==
             {:error, %Vws.Links.Transport.Error{reason: :econnrefused}}
  end

  test "listening twice on one port with reuseaddr still fails while the first listens",
       %{endpoint: endpoint} do
    assert {:error, %Vws.Links.Transport.Error{reason: :eaddrinuse}} = Transport.listen(endpoint)
  end
end
