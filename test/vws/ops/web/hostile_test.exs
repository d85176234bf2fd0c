defmodule Vws.Ops.Web.HostileTest do
  # Issue 30: HTTP stays available to its users. Abandoned MTConnect streams, clients holding
  # connections, one address flooding requests — against the real server on loopback, each client
  # bound to its own 127.0.0.x source address (`ip:` of :gen_tcp.connect).
  use ExUnit.Case, async: false

  alias Vws.Test.{Eventually, MTCClient}

  defp web(opts) do
    pid = start_supervised!({Vws.Ops.Web, [port: 0, interval: 60_000] ++ opts}, id: make_ref())
    {pid, Vws.Ops.Web.port(pid)}
  end

  defp total(web), do: web |> Vws.Ops.Web.connections() |> elem(0)

  defp connect(port, ip, opts \\ []) do
    {:ok, socket} =
      :gen_tcp.connect(
        {127, 0, 0, 1},
        port,
        [:binary, active: false, packet: :raw, ip: ip] ++ opts,
        10_000
      )

    socket
  end

  # Sends a GET and reads the answer's status line and headers: {status, headers}.
  defp head(socket, path) do
    :ok = :gen_tcp.send(socket, "GET #{path} HTTP/1.1\r\nhost: x\r\n\r\n")
    :ok = :inet.setopts(socket, packet: :http_bin)

    case :gen_tcp.recv(socket, 0, 15_000) do
      {:ok, {:http_response, _, status, _}} -> {status, headers(socket, %{})}
      {:error, _} = error -> error
    end
  end

  defp headers(socket, acc) do
    case :gen_tcp.recv(socket, 0, 15_000) do
      {:ok, :http_eoh} ->
        :ok = :inet.setopts(socket, packet: :raw)
        acc

      {:ok, {:http_header, _, name, _, value}} ->
        headers(socket, Map.put(acc, String.downcase(to_string(name)), value))

      {:error, _} ->
        acc
    end
  end

  # One whole GET on a fresh connection from `ip`: {status, body}.
  defp get(port, ip, path) do
    socket = connect(port, ip)

    :ok = :gen_tcp.send(socket, "GET #{path} HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")

    answer = read_all(socket, "")
    :gen_tcp.close(socket)

    case answer do
      "HTTP/1.1 " <> <<status::binary-size(3), _::binary>> ->
        [_, body] = :binary.split(answer, "\r\n\r\n")
        {String.to_integer(status), body}

      other ->
        {:no_answer, other}
    end
  end

  defp read_all(socket, acc) do
    case :gen_tcp.recv(socket, 0, 30_000) do
      {:ok, data} -> read_all(socket, acc <> data)
      {:error, _} -> acc
    end
  end

  # Opens a stream from `ip` and waits until the server counts it.
  defp open_stream(web, port, ip, path) do
    before = held(web, ip)
    socket = connect(port, ip)
    assert {200, %{"content-type" => "multipart/x-mixed-replace" <> _}} = head(socket, path)
    assert Eventually.eventually(fn -> held(web, ip) == before + 1 end)
    socket
  end

  defp held(web, ip), do: web |> Vws.Ops.Web.connections() |> elem(1) |> Map.get(ip, 0)

  test "1,100 abandoned streams (request, headers, close): /current answers within 15 s and no connection is left" do
    {web, port} = web([])

    # from 20 addresses, 200 at a time: each sends its stream request, reads the headers, leaves
    1..1_100
    |> Task.async_stream(
      fn i ->
        socket = connect(port, {127, 0, 0, 10 + rem(i, 20)})
        path = if rem(i, 2) == 0, do: "/current?interval=10000", else: "/sample?interval=10000"
        answer = head(socket, path)
        :gen_tcp.close(socket)
        answer
      end,
      max_concurrency: 200,
      timeout: 60_000
    )
    |> Enum.each(fn {:ok, answer} -> assert match?({s, _} when s in [200, 503], answer) end)

    parent = self()
    spawn_link(fn -> send(parent, {:current, get(port, {127, 0, 0, 2}, "/current")}) end)
    assert_receive {:current, {200, body}}, 15_000
    assert body =~ "MTConnectStreams"

    # the streams ended with their clients, long before their 10 s interval
    assert Eventually.eventually(fn -> total(web) == 0 end, 5_000),
           inspect(Vws.Ops.Web.connections(web))
  end

  test "a stream ends as soon as its client goes, whatever it is waiting for" do
    {web, port} = web([])

    for path <- ["/current?interval=10000", "/sample?interval=10000&heartbeat=10000"] do
      socket = open_stream(web, port, {127, 0, 0, 1}, path)
      :gen_tcp.close(socket)
      # its interval and heartbeat are 10 s: it is gone well before
      assert Eventually.eventually(fn -> total(web) == 0 end, 5_000)
    end
  end

  test "a stream's interval and heartbeat are at most 10 s; beyond, OUT_OF_RANGE" do
    {_web, port} = web([])

    for path <- [
          "/current?interval=2147483646",
          "/current?interval=10001",
          "/sample?interval=10001",
          "/sample?interval=100&heartbeat=10001"
        ] do
      assert {400, "application/xml", body} = MTCClient.get(port, path)
      assert body =~ ~s(errorCode="OUT_OF_RANGE"), body
      assert body =~ "between 0 and 10000" or body =~ "between"
    end

    {ref, pid, head} = MTCClient.stream(port, "/current?interval=10000")
    assert head.status == 200
    assert_receive {:mtc_part, ^ref, _}, 5_000
    MTCClient.stop(pid)
  end

  test "a stream's parts are paced as requests of its client" do
    {_web, port} = web(max_client_rate: 5)
    {ref, pid, _head} = MTCClient.stream(port, "/current?interval=0")
    Process.sleep(2_000)
    MTCClient.stop(pid)
    parts = count_parts(ref, 0)
    # unpaced, a part every 10 ms: about 200; paced at 5 a second: at most 11, a burst of 5 and
    # the first
    assert parts >= 2 and parts <= 18, "#{parts} parts in 2 s"
  end

  defp count_parts(ref, n) do
    receive do
      {:mtc_part, ^ref, _} -> count_parts(ref, n + 1)
    after
      0 -> n
    end
  end

  test "when the server is full, the connection idle the longest is closed for a new client" do
    {web, port} = web(max_connections: 6)

    idle =
      for i <- 1..6 do
        socket = connect(port, {127, 0, 0, 1}, active: true)
        assert Eventually.eventually(fn -> total(web) == i end)
        Process.sleep(5)
        socket
      end

    [oldest | others] = idle
    assert {200, _} = get(port, {127, 0, 0, 2}, "/api/state")
    assert_receive {:tcp_closed, ^oldest}, 5_000
    for s <- others, do: refute_received({:tcp_closed, ^s})
    Enum.each(others, &:gen_tcp.close/1)
  end

  test "each client has its own share of connections: one address holding streams does not lock out another" do
    {web, port} = web(max_connections: 8, max_client_connections: 4)

    streams = for _ <- 1..4, do: open_stream(web, port, {127, 0, 0, 1}, "/current?interval=5000")

    # the client at its share, with nothing idle to close: refused, at once
    assert {503, "busy: too many connections from your address"} =
             get(port, {127, 0, 0, 1}, "/api/state")

    # another client is served
    assert {200, _} = get(port, {127, 0, 0, 2}, "/api/state")

    # four more addresses fill the server with streams: a newcomer then takes the oldest stream of
    # the client holding the most
    assert Eventually.eventually(fn -> total(web) == 4 end)
    more = for i <- 3..6, do: open_stream(web, port, {127, 0, 0, i}, "/current?interval=5000")

    assert total(web) == 8
    [first | _] = streams
    :ok = :inet.setopts(first, active: true)
    assert {200, _} = get(port, {127, 0, 0, 7}, "/api/state")
    assert_receive {:tcp_closed, ^first}, 5_000

    Enum.each(streams ++ more, &:gen_tcp.close/1)
    assert Eventually.eventually(fn -> total(web) == 0 end)
  end

  test "an address reconnecting as fast as it is closed is refused beyond its connection rate, closing nobody" do
    {web, port} = web(max_connections: 25, max_client_connect_rate: 5)

    others =
      for i <- 1..20 do
        socket = connect(port, {127, 0, 0, 9 + i}, active: true)
        assert Eventually.eventually(fn -> total(web) == i end)
        socket
      end

    # 40 at once from one address: 10 (a burst of two seconds' worth) get in, closing the other
    # address's connections idle the longest; the rest are refused at once, closing nobody
    answers =
      for _ <- 1..40 do
        socket = connect(port, {127, 0, 0, 1})

        :ok =
          :gen_tcp.send(socket, "GET /api/state HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")

        socket
      end
      |> Enum.map(fn socket ->
        answer = read_all(socket, "")
        :gen_tcp.close(socket)
        answer
      end)

    refused = Enum.count(answers, &(&1 =~ "too many new connections from your address"))
    served = Enum.count(answers, &String.starts_with?(&1, "HTTP/1.1 200"))
    assert refused >= 25 and served >= 10, "#{served} served, #{refused} refused"

    closed =
      Enum.count(others, fn s -> receive(do: ({:tcp_closed, ^s} -> true), after: (0 -> false)) end)

    assert closed <= served
    Enum.each(others, &:gen_tcp.close/1)
  end

  test "one address flooding requests waits behind its own: another address is served" do
    # a request held more than 2 s is refused (10 s by default: the same rule, sooner)
    {_web, port} = web(max_client_rate: 2, max_rate: 1_000, max_wait: 2_000)
    parent = self()
    stop = :atomics.new(1, [])
    started = System.monotonic_time(:millisecond)

    flooders =
      for _ <- 1..30 do
        spawn_link(fn ->
          statuses =
            Stream.repeatedly(fn -> get(port, {127, 0, 0, 1}, "/api/state") end)
            |> Enum.reduce_while([], fn {status, _}, acc ->
              if :atomics.get(stop, 1) == 1,
                do: {:halt, [status | acc]},
                else: {:cont, [status | acc]}
            end)

          send(parent, {:flooded, statuses})
        end)
      end

    # the flood is on: the flooder's own requests are refused beyond its 2 s of waiting
    Process.sleep(1_000)

    spawn_link(fn -> send(parent, {:honest, get(port, {127, 0, 0, 2}, "/api/state")}) end)
    assert_receive {:honest, {200, body}}, 5_000
    assert body =~ "workstations"

    :atomics.put(stop, 1, 1)

    statuses =
      Enum.flat_map(flooders, fn _ ->
        assert_receive {:flooded, s}, 30_000
        s
      end)

    seconds = (System.monotonic_time(:millisecond) - started) / 1000
    assert 503 in statuses
    # at most 2 a second (a burst of 2, and the first)
    assert Enum.count(statuses, &(&1 == 200)) <= 2 * seconds + 4
  end
end
