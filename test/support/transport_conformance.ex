defmodule Vws.TransportConformance do
  @moduledoc """
  The behaviour every listenable `Vws.Links.Transport` must show, as ExUnit tests.

      use Vws.TransportConformance, listen_on: fn -> "tcp://127.0.0.1:0" end

  `listen_on` returns a fresh endpoint string to listen on; each test gets a listener, a client
  connection and the accepted server connection, all owned by the test process. `armed` (default
  1): how many deliveries one `activate/1` lets through at most (TCP arms eight,
  `Vws.Links.Transport.TCP`).
  """

  defmacro __using__(opts) do
    listen_on = Keyword.fetch!(opts, :listen_on)
    armed = Keyword.get(opts, :armed, 1)

    quote do
      import Vws.TransportHelpers

      alias Vws.Links.Transport

      setup do
        {:ok, listener} = Transport.listen(unquote(listen_on).())
        endpoint = Transport.listener_endpoint(listener)
        {:ok, client} = Transport.connect(endpoint)
        {:ok, server} = Transport.accept(listener, 5000)
        on_exit(fn -> Transport.close_listener(listener) end)
        %{listener: listener, endpoint: endpoint, client: client, server: server}
      end

      describe "conformance:" do
        test "bytes flow both ways", %{client: client, server: server} do
          assert Transport.send(client, ["DO ", ["MOVE" | "\r\n"]]) == :ok
          assert recv_exactly(server, 9) == "DO MOVE\r\n"
          assert Transport.send(server, <<0, 255, 13, 10>>) == :ok
          assert recv_exactly(client, 4) == <<0, 255, 13, 10>>
          assert is_binary(Transport.peer(client)) and is_binary(Transport.peer(server))
        end

        test "the conns carry the endpoint they were made through", ctx do
          assert ctx.client.endpoint == ctx.endpoint
          assert ctx.server.endpoint == ctx.endpoint
          assert ctx.client.module == ctx.server.module
        end

        test "nothing arrives before activate, and at most #{unquote(armed)} deliveries per activate",
             ctx do
          %{client: client, server: server} = ctx
          :ok = Transport.send(client, "first")
          refute_receive _, 100

          :ok = Transport.activate(server)
          assert next(server) == {:data, "first"}

          # one send at a time, each waited for: as many as are armed arrive without an activate,
          # then nothing does (a used-up TCP socket says so with no bytes)
          delivered =
            Enum.map(2..(unquote(armed) + 2), fn i ->
              :ok = Transport.send(client, "m#{i}")

              case next(server, 300) do
                {:data, "m" <> _ = bytes} -> bytes
                {:data, ""} -> :passive
                :timeout -> :held
              end
            end)

          sent = Enum.map(2..(unquote(armed) + 2), &"m#{&1}")
          {through, held} = Enum.split(delivered, unquote(armed) - 1)
          assert through == Enum.take(sent, unquote(armed) - 1)
          assert :held in held and Enum.all?(held, &(&1 in [:passive, :held]))
          refute_receive _, 100

          # the held bytes come with the next activate, in order
          rest = sent |> Enum.drop(unquote(armed) - 1) |> Enum.join()
          assert recv_exactly(server, byte_size(rest)) == rest
        end

        test "activate_once: nothing arrives before it, one message per call", ctx do
          %{client: client, server: server} = ctx
          :ok = Transport.send(client, "first")
          refute_receive _, 100

          :ok = Transport.activate_once(server)
          assert next(server) == {:data, "first"}

          :ok = Transport.send(client, "second")
          refute_receive _, 100
          :ok = Transport.activate_once(server)
          assert next(server) == {:data, "second"}
        end

        test "a close is seen by the peer after the bytes sent before it", ctx do
          %{client: client, server: server} = ctx
          :ok = Transport.send(client, "last words")
          :ok = Transport.close(client)
          assert recv_exactly(server, 10) == "last words"
          assert_closed(server)
          assert {:error, _} = Transport.send(server, "anyone?")
          assert Transport.close(server) == :ok
          assert Transport.close(server) == :ok
        end

        test "the server closing is seen by the client", %{client: client, server: server} do
          :ok = Transport.close(server)
          assert_closed(client)
        end

        test "the controlling process dying closes the connection", ctx do
          %{server: server, endpoint: endpoint, listener: listener} = ctx
          test = self()

          {pid, monitor} =
            spawn_monitor(fn ->
              {:ok, conn} = Transport.connect(endpoint)
              :ok = Transport.send(conn, "hello from a short life")
              send(test, :sent)
            end)

          assert_receive :sent
          assert_receive {:DOWN, ^monitor, :process, ^pid, :normal}
          {:ok, orphan_peer} = Transport.accept(listener, 5000)
          assert recv_exactly(orphan_peer, 23) == "hello from a short life"
          assert_closed(orphan_peer)
          assert Transport.send(server, "still fine") == :ok
        end

        test "controlling_process hands delivery to another process", ctx do
          %{client: client, server: server} = ctx
          test = self()

          new_owner =
            spawn_link(fn ->
              receive do
                :go -> send(test, {:got, recv_exactly(server, 5)})
              end
            end)

          assert Transport.controlling_process(server, new_owner) == :ok
          :ok = Transport.send(client, "hello")
          send(new_owner, :go)
          assert_receive {:got, "hello"}, 5000
        end

        test "only the controlling process may hand it over", %{server: server} do
          test = self()

          spawn_link(fn ->
            send(test, {:result, Transport.controlling_process(server, self())})
          end)

          assert_receive {:result, {:error, %Vws.Links.Transport.Error{reason: :not_owner}}}
        end

        test "1 MB in uneven chunks arrives intact and in order, both ways", ctx do
          %{client: client, server: server} = ctx
          data = :crypto.strong_rand_bytes(1_048_576)
          chunks = chunk(data, [1, 7, 1000, 65_536, 3, 250_000])

          for {from, to} <- [{client, server}, {server, client}] do
            sender = Task.async(fn -> Enum.each(chunks, &(:ok = Transport.send(from, &1))) end)
            assert recv_exactly(to, byte_size(data), 20_000) == data
            Task.await(sender, 20_000)
          end
        end

        test "messages of other connections are :unknown", ctx do
          %{client: client, server: server, endpoint: endpoint, listener: listener} = ctx
          {:ok, other_client} = Transport.connect(endpoint)
          {:ok, other_server} = Transport.accept(listener, 5000)
          :ok = Transport.send(other_client, "not yours")
          :ok = Transport.activate(other_server)
          assert_receive msg, 5000
          assert Transport.handle_message(server, msg) == :unknown
          assert Transport.handle_message(client, msg) == :unknown
          assert Transport.handle_message(other_server, msg) == {:data, "not yours"}
          assert Transport.handle_message(server, {:tcp, :nope, "x"}) == :unknown
          assert Transport.handle_message(server, :junk) == :unknown
        end

        test "accept times out when nobody connects", %{listener: listener} do
          assert Transport.accept(listener, 50) ==
                   {:error, %Vws.Links.Transport.Error{reason: :timeout}}
        end

        test "a closed listener accepts no more connections", ctx do
          %{listener: listener, endpoint: endpoint, client: client} = ctx
          assert Transport.close_listener(listener) == :ok
          assert {:error, _} = Transport.connect(endpoint)
          # Established connections live on.
          assert Transport.send(client, "still here") == :ok
        end
      end

      defp chunk(data, sizes) do
        Stream.cycle(sizes)
        |> Enum.reduce_while({data, []}, fn
          _size, {<<>>, acc} ->
            {:halt, Enum.reverse(acc)}

          size, {rest, acc} when byte_size(rest) <= size ->
            {:halt, Enum.reverse([rest | acc])}

          size, {rest, acc} ->
            {:cont,
             {binary_part(rest, size, byte_size(rest) - size), [binary_part(rest, 0, size) | acc]}}
        end)
      end
    end
  end
end
