defmodule Vws.Links.Transport.LoopbackTest do
  use ExUnit.Case, async: true
  use Vws.TransportConformance, listen_on: &Vws.Links.Transport.LoopbackTest.fresh_name/0

  alias Vws.Links.Transport.Loopback

  def fresh_name, do: "loopback:test-#{System.unique_integer([:positive])}"

  test "connecting to a name nobody listens on is refused" do
    assert Transport.connect(fresh_name()) ==
             {:error, %Vws.Links.Transport.Error{reason: :econnrefused}}
  end

  test "a name can be listened on once; closing the listener frees it", ctx do
    assert Transport.listen(ctx.endpoint) ==
             {:error, %Vws.Links.Transport.Error{reason: :eaddrinuse}}

    :ok = Transport.close_listener(ctx.listener)
    {:ok, again} = Transport.listen(ctx.endpoint)
    :ok = Transport.close_listener(again)
  end

  test "the listener goes away with the process that opened it" do
    name = fresh_name()
    test = self()

    {pid, monitor} =
      spawn_monitor(fn ->
        {:ok, _listener} = Transport.listen(name)
        send(test, :listening)
      end)

    assert_receive :listening
    assert_receive {:DOWN, ^monitor, :process, ^pid, :normal}

    wait_until(fn ->
      Transport.connect(name) == {:error, %Vws.Links.Transport.Error{reason: :econnrefused}}
    end)
  end

  test "connections not yet accepted are closed with the listener" do
    {:ok, listener} = Transport.listen(fresh_name())
    {:ok, client} = Transport.connect(Transport.listener_endpoint(listener))
    :ok = Transport.close_listener(listener)
    assert_closed(client)

    assert Transport.accept(listener, 100) ==
             {:error, %Vws.Links.Transport.Error{reason: :closed}}
  end

  test "connect succeeds before accept, like a TCP backlog, and keeps what was sent" do
    {:ok, listener} = Transport.listen(fresh_name(), backlog: 2)
    endpoint = Transport.listener_endpoint(listener)
    {:ok, c1} = Transport.connect(endpoint)
    {:ok, _c2} = Transport.connect(endpoint)

    assert Transport.connect(endpoint) ==
             {:error, %Vws.Links.Transport.Error{reason: :econnrefused}}

    :ok = Transport.send(c1, "early")
    {:ok, s1} = Transport.accept(listener, 1000)
    assert recv_exactly(s1, 5) == "early"
    :ok = Transport.close_listener(listener)
  end

  test "an acceptor waiting before the connect gets it" do
    {:ok, listener} = Transport.listen(fresh_name())
    test = self()

    acceptor =
      spawn_link(fn ->
        {:ok, server} = Transport.accept(listener, :infinity)
        send(test, {:accepted, recv_exactly(server, 2)})
      end)

    wait_until(fn -> {:messages, []} == Process.info(acceptor, :messages) end)
    {:ok, client} = Transport.connect(Transport.listener_endpoint(listener))
    :ok = Transport.send(client, "hi")
    assert_receive {:accepted, "hi"}, 5000
  end

  test "the messages carry the side's ref", %{client: client, server: server} do
    :ok = Transport.send(client, "x")
    :ok = Transport.activate(server)
    %Loopback{ref: ref} = server.handle
    assert_receive {:vws_loopback, ^ref, "x"}
    assert Transport.peer(server) == "#{server.endpoint} (client)"
    assert Transport.peer(client) == "#{client.endpoint} (server)"
  end

  test "a sender is held back while the receiver does not read (bounded buffer)", ctx do
    %{client: client, server: server} = ctx
    chunk = :binary.copy(<<7>>, 65_536)
    sender = Task.async(fn -> for _ <- 1..48, do: :ok = Transport.send(client, chunk) end)
    pair = client.handle.pair

    # 3 MB offered, nobody reading: the pair holds at most its high-water mark plus one chunk,
    # and the sender waits.
    wait_until(fn -> not :queue.is_empty(:sys.get_state(pair).server.writers) end)
    assert :sys.get_state(pair).server.inbox_size <= 1_048_576 + 65_536
    assert Task.yield(sender, 0) == nil

    assert recv_exactly(server, 48 * 65_536) == :binary.copy(chunk, 48)
    Task.await(sender)
  end

  test "writers blocked on a full peer fail when the peer closes", ctx do
    %{client: client, server: server} = ctx
    big = :binary.copy(<<1>>, 1_048_576)
    :ok = Transport.send(client, big)
    sender = Task.async(fn -> Transport.send(client, "more") end)
    pair = client.handle.pair
    wait_until(fn -> not :queue.is_empty(:sys.get_state(pair).server.writers) end)
    :ok = Transport.close(server)
    assert Task.await(sender) == {:error, %Vws.Links.Transport.Error{reason: :closed}}
  end

  test "thousands of pairs are cheap and leave nothing behind" do
    {:ok, listener} = Transport.listen(fresh_name())
    endpoint = Transport.listener_endpoint(listener)

    pairs =
      for i <- 1..2000 do
        {:ok, client} = Transport.connect(endpoint)
        {:ok, server} = Transport.accept(listener, 1000)
        :ok = Transport.send(client, <<i::16>>)
        {client, server, i}
      end

    # One small process per pair, nothing else.
    processes = pairs |> Enum.map(fn {client, _, _} -> client.handle.pair end) |> Enum.uniq()
    assert length(processes) == 2000

    assert Enum.all?(pairs, fn {client, server, _} -> client.handle.pair == server.handle.pair end)

    bytes = processes |> Enum.map(&elem(Process.info(&1, :memory), 1)) |> Enum.sum()
    assert div(bytes, 2000) < 16_384

    for {client, server, i} <- pairs do
      assert recv_exactly(server, 2) == <<i::16>>
      :ok = Transport.close(client)
      assert_closed(server)
      :ok = Transport.close(server)
    end

    wait_until(fn -> not Enum.any?(processes, &Process.alive?/1) end)
    :ok = Transport.close_listener(listener)
  end

  test "endpoints built in code may use any term as the name" do
    endpoint = %Vws.Links.Endpoint{kind: :loopback, name: {:ws, 1, :dnc}}
    {:ok, listener} = Transport.listen(endpoint)
    {:ok, client} = Transport.connect(endpoint)
    {:ok, server} = Transport.accept(listener, 1000)
    :ok = Transport.send(server, "ok")
    assert recv_exactly(client, 2) == "ok"
    :ok = Transport.close_listener(listener)
  end
end
