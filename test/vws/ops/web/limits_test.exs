defmodule Vws.Ops.Web.LimitsTest do
  # The attacks of issue 16 against the dashboard's HTTP server, from plain TCP clients: a huge
  # body and a huge URI (memory), idle and trickling connections (starvation), and the tokens;
  # and the bounds of the head reader (a line at the limit, a body or a request read with a head).
  # Not async: the memory assertions want the node to themselves.
  use ExUnit.Case, async: false

  @big 300 * 1024 * 1024

  defp web(opts) do
    pid = start_supervised!({Vws.Ops.Web, [port: 0] ++ opts}, id: make_ref())
    Vws.Ops.Web.port(pid)
  end

  defp connect(port, opts \\ []) do
    {:ok, socket} =
      :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, packet: :raw] ++ opts)

    socket
  end

  # A whole answer to one request on a fresh connection: {status, headers, body}.
  defp request(port, head, timeout \\ 10_000) do
    socket = connect(port)
    :ok = :gen_tcp.send(socket, head)
    answer = read_answer(socket, timeout)
    :gen_tcp.close(socket)
    answer
  end

  defp get(port, path, headers \\ "") do
    request(port, "GET #{path} HTTP/1.1\r\nhost: x\r\nconnection: close\r\n#{headers}\r\n")
  end

  defp read_answer(socket, timeout) do
    :ok = :inet.setopts(socket, packet: :http_bin)
    {:ok, {:http_response, _, status, _}} = :gen_tcp.recv(socket, 0, timeout)
    headers = read_headers(socket, timeout, %{})
    :ok = :inet.setopts(socket, packet: :raw)
    length = String.to_integer(headers["content-length"] || "0")
    {:ok, body} = if length > 0, do: :gen_tcp.recv(socket, length, timeout), else: {:ok, ""}
    {status, headers, body}
  end

  defp read_headers(socket, timeout, acc) do
    case :gen_tcp.recv(socket, 0, timeout) do
      {:ok, :http_eoh} ->
        acc

      {:ok, {:http_header, _, name, _, value}} ->
        read_headers(socket, timeout, Map.put(acc, String.downcase(to_string(name)), value))
    end
  end

  # Samples the node's memory every 5 ms until told to stop; answers the highest total seen.
  defp memory_peak do
    parent = self()

    spawn_link(fn ->
      loop = fn loop, peak ->
        receive do
          :stop -> send(parent, {:peak, peak})
        after
          5 -> loop.(loop, max(peak, :erlang.memory(:total)))
        end
      end

      loop.(loop, :erlang.memory(:total))
    end)
  end

  defp stop_peak(sampler) do
    send(sampler, :stop)
    assert_receive {:peak, peak}, 5_000
    peak
  end

  # Sends `total` bytes of body in 1 MB writes from a process of its own until the server stops
  # taking them; reports how many it could send.
  defp stream_body(socket, total) do
    parent = self()
    chunk = :binary.copy("x", 1024 * 1024)

    spawn(fn ->
      sent =
        Enum.reduce_while(1..div(total, byte_size(chunk)), 0, fn _, sent ->
          case :gen_tcp.send(socket, chunk) do
            :ok -> {:cont, sent + byte_size(chunk)}
            {:error, _} -> {:halt, sent}
          end
        end)

      send(parent, {:body_sent, sent})
    end)
  end

  test "a 300 MB POST to the control path without the token: 403 at once, its body never read, memory bounded" do
    port = web(token: "s3cret")
    :erlang.garbage_collect()
    before = :erlang.memory(:total)
    sampler = memory_peak()
    socket = connect(port)
    started = System.monotonic_time(:millisecond)

    :ok =
      :gen_tcp.send(
        socket,
        "POST /api/status?ws=VWS&name=VISE HTTP/1.1\r\nhost: x\r\ncontent-length: #{@big}\r\n" <>
          "x-vws-token: wrong\r\n\r\n"
      )

    stream_body(socket, @big)
    assert {403, _, body} = read_answer(socket, 10_000)
    assert body =~ "x-vws-token"
    assert System.monotonic_time(:millisecond) - started < 5_000
    assert_receive {:body_sent, sent}, 30_000
    assert sent < 64 * 1024 * 1024, "the server took #{sent} bytes of a refused body"
    assert stop_peak(sampler) - before < 50 * 1024 * 1024
    :gen_tcp.close(socket)
  end

  test "a 300 MB POST with the right token: 413 by its Content-Length, memory bounded" do
    port = web(token: "s3cret")
    :erlang.garbage_collect()
    before = :erlang.memory(:total)
    sampler = memory_peak()
    socket = connect(port)

    :ok =
      :gen_tcp.send(
        socket,
        "POST /api/status?ws=VWS&name=VISE HTTP/1.1\r\nhost: x\r\ncontent-length: #{@big}\r\n" <>
          "x-vws-token: s3cret\r\n\r\n"
      )

    stream_body(socket, @big)
    assert {413, %{"connection" => "close"}, _} = read_answer(socket, 10_000)
    assert_receive {:body_sent, sent}, 30_000
    assert sent < 64 * 1024 * 1024
    assert stop_peak(sampler) - before < 50 * 1024 * 1024
    :gen_tcp.close(socket)

    # a body without a length is not read either
    assert {411, _, _} =
             request(
               port,
               "POST /api/status HTTP/1.1\r\nhost: x\r\ntransfer-encoding: chunked\r\n" <>
                 "x-vws-token: s3cret\r\n\r\n"
             )
  end

  test "a 4 MB URI is answered 414 and a 4 MB header 431 after the first 8 KB, memory bounded" do
    port = web([])
    :erlang.garbage_collect()
    before = :erlang.memory(:total)
    sampler = memory_peak()
    long = :binary.copy("a", 4 * 1024 * 1024)

    for {head, status} <- [
          {"GET /#{long} HTTP/1.1\r\nhost: x\r\n\r\n", 414},
          {"GET / HTTP/1.1\r\nhost: x\r\nx-long: #{long}\r\n\r\n", 431}
        ] do
      socket = connect(port)
      parent = self()
      spawn(fn -> send(parent, {:sent, :gen_tcp.send(socket, head)}) end)
      # answered while the client is still sending, then closed
      assert {^status, %{"connection" => "close"}, _} = read_answer(socket, 10_000)
      assert {:error, _} = :gen_tcp.recv(socket, 0, 10_000)
      assert_receive {:sent, _}, 10_000
      :gen_tcp.close(socket)
    end

    assert stop_peak(sampler) - before < 50 * 1024 * 1024

    many = for i <- 1..100, into: "", do: "x-h#{i}: v\r\n"
    assert {431, _, _} = request(port, "GET / HTTP/1.1\r\nhost: x\r\n#{many}\r\n")
    assert {200, _, _} = get(port, "/api/state")
  end

  test "a request line or a header line of max_line bytes (CR LF included) is read, one byte more is refused" do
    port = web([])
    max = Vws.Ops.Web.Server.defaults()[:max_line]
    # "GET /api/state?p=" <> pad <> " HTTP/1.1\r\n" and "x-pad: " <> pad <> "\r\n" of `size` bytes
    uri = fn size -> "/api/state?p=" <> :binary.copy("a", size - 28) end
    header = fn size -> "x-pad: " <> :binary.copy("a", size - 9) <> "\r\n" end
    assert byte_size("GET #{uri.(max)} HTTP/1.1\r\n") == max
    assert byte_size(header.(max)) == max

    assert {200, _, _} = get(port, uri.(max))

    assert {414, %{"connection" => "close"}, "request line longer than 8192 bytes"} =
             get(port, uri.(max + 1))

    assert {200, _, _} = get(port, "/api/state", header.(max))

    assert {431, %{"connection" => "close"}, "header line longer than 8192 bytes"} =
             get(port, "/api/state", header.(max + 1))

    # lines may end in a bare LF, as OTP's HTTP parser allows
    assert {200, _, _} = request(port, "GET /api/state HTTP/1.1\nhost: x\nconnection: close\n\n")
  end

  test "a body that comes with its head, whole or in part, is read; what follows it is the next request" do
    port = web(token: "s3cret", body_timeout: 1_000)
    body = ~s({"a": 1, "b": "GET / HTTP/1.1"})

    post =
      "POST /api/status?ws=NOPE&name=VISE HTTP/1.1\r\nhost: x\r\nx-vws-token: s3cret\r\n" <>
        "content-length: #{byte_size(body)}\r\n\r\n"

    next = "GET /api/state HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n"

    # head, body and the next request in one write
    socket = connect(port)
    :ok = :gen_tcp.send(socket, post <> body <> next)
    assert {404, %{"connection" => "keep-alive"}, answer} = read_answer(socket, 5_000)
    assert answer =~ "no workstation NOPE"
    assert {200, %{"content-type" => "application/json"}, _} = read_answer(socket, 5_000)
    :gen_tcp.close(socket)

    # the head and the first bytes of the body in one write, the rest later
    socket = connect(port)
    {first, rest} = String.split_at(body, 5)
    :ok = :gen_tcp.send(socket, post <> first)
    Process.sleep(100)
    :ok = :gen_tcp.send(socket, rest <> next)
    assert {404, _, _} = read_answer(socket, 5_000)
    assert {200, _, _} = read_answer(socket, 5_000)
    :gen_tcp.close(socket)
  end

  test "two GETs pipelined in one write on a kept-alive connection are both answered, in order" do
    port = web([])
    socket = connect(port)

    :ok =
      :gen_tcp.send(
        socket,
        "GET /api/state HTTP/1.1\r\nhost: x\r\n\r\nGET / HTTP/1.1\r\nhost: x\r\n\r\n"
      )

    assert {200, %{"content-type" => "application/json", "connection" => "keep-alive"}, _} =
             read_answer(socket, 5_000)

    assert {200, %{"content-type" => "text/html" <> _, "connection" => "keep-alive"}, html} =
             read_answer(socket, 5_000)

    assert html =~ "<title>VWS dashboard</title>"
    # and the connection is still there for a third
    :ok = :gen_tcp.send(socket, "GET /api/state HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
    assert {200, %{"connection" => "close"}, _} = read_answer(socket, 5_000)
    :gen_tcp.close(socket)
  end

  test "a GET is answered while 60 idle connections are open" do
    port = web([])
    idle = for _ <- 1..60, do: connect(port)
    # and 60 more that started a request and stopped
    half = for _ <- 1..60, do: connect(port) |> tap(&:gen_tcp.send(&1, "GET / HTTP/1.1\r\nho"))

    started = System.monotonic_time(:millisecond)
    assert {200, %{"content-type" => "application/json"}, _} = get(port, "/api/state")
    assert {200, _, body} = get(port, "/")
    assert body =~ "<title>VWS dashboard</title>"
    assert System.monotonic_time(:millisecond) - started < 5_000
    Enum.each(idle ++ half, &:gen_tcp.close/1)
  end

  test "idle and trickling clients are closed when their time is up, whatever they send" do
    port = web(head_timeout: 1_000, idle_timeout: 500)
    idle = connect(port, active: true)
    trickler = connect(port, active: true)
    parent = self()

    spawn_link(fn ->
      # one byte every 50 ms of a request line that never ends
      Enum.reduce_while(Stream.cycle(["G", "E", "T", " ", "/", "a"]), 0, fn byte, n ->
        Process.sleep(50)

        case :gen_tcp.send(trickler, byte) do
          :ok -> {:cont, n + 1}
          {:error, _} -> send(parent, {:trickled, n}) && {:halt, n}
        end
      end)
    end)

    # others are served meanwhile
    assert {200, _, _} = get(port, "/api/state")
    started = System.monotonic_time(:millisecond)
    assert_receive {:tcp_closed, ^idle}, 5_000
    assert_receive {:tcp_closed, ^trickler}, 5_000
    assert System.monotonic_time(:millisecond) - started < 3_000
    assert_receive {:trickled, n}, 5_000
    assert n < 60

    # a kept-alive connection is closed after idle_timeout, having been answered
    socket = connect(port)
    :ok = :gen_tcp.send(socket, "GET /api/state HTTP/1.1\r\nhost: x\r\n\r\n")
    assert {200, %{"connection" => "keep-alive"}, _} = read_answer(socket, 5_000)
    :ok = :gen_tcp.send(socket, "GET /api/state HTTP/1.1\r\nhost: x\r\n\r\n")
    assert {200, _, _} = read_answer(socket, 5_000)
    assert {:error, :closed} = :gen_tcp.recv(socket, 0, 5_000)
  end

  test "a read token: reads need it (Basic password or x-vws-token), the control token reads too" do
    port = web(read_token: "look", token: "act")

    assert {401, %{"www-authenticate" => "Basic realm=\"VWS\"" <> _}, _} = get(port, "/api/state")

    assert {401, _, _} = get(port, "/probe")
    assert {401, _, _} = get(port, "/", "x-vws-token: wrong\r\n")
    basic = "authorization: Basic #{Base.encode64("anyone:look")}\r\n"
    assert {200, _, _} = get(port, "/api/state", basic)
    assert {200, _, _} = get(port, "/", "x-vws-token: look\r\n")
    assert {200, _, _} = get(port, "/api/state", "x-vws-token: act\r\n")

    # the read token does not control
    assert {403, _, _} =
             request(
               port,
               "POST /api/status?ws=X&name=VISE HTTP/1.1\r\nhost: x\r\nx-vws-token: look\r\n\r\n"
             )
  end
end
