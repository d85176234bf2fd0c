defmodule Vws.Ops.Web.Conn do
  @moduledoc false
  # One HTTP connection of `Vws.Ops.Web.Server`, in a process of its own: reads each request's head
  # within its deadline (the socket is raw; OTP's HTTP parser takes the head line by line from a
  # buffer bounded by `max_line`, see next_line/2), asks the handler whether the request is
  # allowed, reads the body only then, answers, and keeps the connection alive while the client
  # wants it and the limits allow. A request line or a header line longer than `max_line` is
  # answered 414 or 431 and the connection closed. See `Vws.Ops.Web.Server` for the limits.

  alias Vws.Ops.Web.{Clients, Handler}

  @doc false
  # `pace`: the client's own request pace (Vws.Ops.Web.Clients)
  def serve(socket, pace, conf) do
    Process.flag(:priority, :low)
    loop(socket, Map.put(conf, :client_pace, pace), 1, conf.limits.head_timeout, "")
  end

  @doc false
  # The connection limit is reached: say so and close, without reading anything.
  def refuse_busy(socket, why, conf) do
    _ = respond(socket, {503, "text/plain", why}, false, conf, nil)
    :socket.close(socket)
  end

  # `buffer`: bytes read from the socket but not used yet — the start of the next request when the
  # client sent it along with the previous one (pipelining).
  # While it waits for a request's head the connection is idle (Vws.Ops.Web.Clients may close it
  # to make room for another client); from the head on it is busy.
  defp loop(socket, conf, n, wait, buffer) do
    deadline = now() + wait
    if n > 1, do: Clients.mark(conf.tables, :idle)

    case read_head(socket, buffer, conf.limits, deadline) do
      {:ok, request, buffer} ->
        Clients.mark(conf.tables, :busy)

        case answer(socket, request, buffer, conf) do
          {:keep, {:stream, _type, _first, _more} = stream, _rest} ->
            Clients.mark(conf.tables, :stream)
            watch_stream(socket, stream, conf, request)

          {:keep, response, rest} ->
            keep = n < conf.limits.max_requests and keep_alive?(request)

            case respond(socket, response, keep, conf, request) do
              :ok when keep -> loop(socket, conf, n + 1, conf.limits.idle_timeout, rest)
              _ -> :socket.close(socket)
            end

          {:close, response} ->
            _ = respond(socket, response, false, conf, request)
            close_unread(socket)
        end

      {:error, {status, why}} ->
        _ = respond(socket, {status, "text/plain", why}, false, conf, nil)
        close_unread(socket)

      {:error, _closed_or_timeout} ->
        :socket.close(socket)
    end
  end

  ## The head

  # The request's head, and what of the bytes read came after it (a body, or the next request).
  defp read_head(socket, buffer, limits, deadline) do
    reader = %{
      socket: socket,
      deadline: deadline,
      max_line: limits.max_line,
      buffer: buffer,
      bytes: 0
    }

    with {:ok, {:http_request, method, uri, version}, reader} <- next_line(reader, :http_bin),
         {:ok, path, query} <- target(uri),
         {:ok, headers, reader} <- read_headers(reader, limits, %{}, 0) do
      {:ok,
       %{
         method: method_name(method),
         started: System.monotonic_time(),
         path: path,
         query: query,
         version: version,
         headers: headers
       }, reader.buffer}
    else
      {:ok, {:http_error, _}, _} -> {:error, {400, "bad request line"}}
      {:ok, _other, _} -> {:error, {400, "bad request"}}
      {:error, :too_long} -> {:error, {414, "request line longer than #{limits.max_line} bytes"}}
      {:error, :bad_target} -> {:error, {400, "bad request target"}}
      {:error, _} = error -> error
    end
  end

  defp read_headers(reader, limits, acc, count) do
    case next_line(reader, :httph_bin) do
      {:ok, :http_eoh, reader} ->
        {:ok, acc, reader}

      {:ok, {:http_header, _, name, _, value}, reader} ->
        count = count + 1

        if count > limits.max_headers or reader.bytes > limits.max_head do
          {:error, {431, "request header fields too large"}}
        else
          name = header_name(name)
          acc = Map.update(acc, name, value, &(&1 <> ", " <> value))
          read_headers(reader, limits, acc, count)
        end

      {:ok, {:http_error, _}, _} ->
        {:error, {400, "bad header line"}}

      {:error, :too_long} ->
        {:error, {431, "header line longer than #{limits.max_line} bytes"}}

      {:error, _} = error ->
        error
    end
  end

  # The next line of the head (`type` :http_bin for the request line, :httph_bin for a header)
  # parsed by OTP's HTTP parser — the one of `packet: :http_bin` — from the front of the buffer,
  # reading from the socket while the buffer holds no whole line, until the head's deadline.
  # `packet_size: max_line` bounds the line, its CR LF included: as soon as max_line bytes without
  # a line end are in, it is too long, so the buffer never holds more than max_line bytes and one
  # read of the socket (at most its `{:otp, :rcvbuf}`, 4096 bytes: Vws.Ops.Web.Server). A header line is only
  # complete once the byte after it is in (a line starting with a space continues a header).
  # `bytes` counts the bytes of head taken so far.
  defp next_line(reader, type) do
    case :erlang.decode_packet(type, reader.buffer, packet_size: reader.max_line) do
      {:ok, packet, rest} ->
        taken = byte_size(reader.buffer) - byte_size(rest)
        {:ok, packet, %{reader | buffer: rest, bytes: reader.bytes + taken}}

      {:more, _} when byte_size(reader.buffer) <= reader.max_line ->
        with {:ok, data} <- recv(reader.socket, reader.deadline) do
          next_line(%{reader | buffer: reader.buffer <> data}, type)
        end

      # {:error, :invalid}, the parser's only error for HTTP lines, is a line longer than
      # packet_size; {:more, _} with more than max_line bytes buffered would be one too (the
      # parser says :invalid first: the guard above only makes the bound plain here)
      _too_long ->
        {:error, :too_long}
    end
  end

  defp header_name(name) when is_atom(name), do: name |> Atom.to_string() |> String.downcase()
  defp header_name(name) when is_binary(name), do: String.downcase(name)

  defp method_name(m) when is_atom(m), do: Atom.to_string(m)
  defp method_name(m) when is_binary(m), do: m

  defp target({:abs_path, raw}) do
    case String.split(raw, "?", parts: 2) do
      [path] -> {:ok, URI.decode(path), %{}}
      [path, q] -> {:ok, URI.decode(path), decode_query(q)}
    end
  rescue
    _ -> {:error, :bad_target}
  end

  defp target({:absoluteURI, _scheme, _host, _port, raw}), do: target({:abs_path, raw})
  defp target(_), do: {:error, :bad_target}

  # a query that cannot be decoded is not dropped: the handler refuses it
  defp decode_query(q) do
    URI.decode_query(q)
  rescue
    _ -> :invalid
  end

  ## Answering

  # Authorize on the head alone; only then read a body (bounded), then let the handler answer.
  # `buffer` holds the bytes read after the head; answers {:keep, response, bytes after the body}
  # or {:close, response}.
  defp answer(socket, request, buffer, conf) do
    case pace(conf) do
      :ok -> authorized(socket, request, buffer, conf)
      :busy -> {:close, {503, "text/plain", "busy: too many requests"}}
    end
  end

  # The request rate: first the client's own (`max_client_rate`), then the server's, all clients
  # together (`max_rate`). Each request takes the next free slot of each (1/rate s apart) and
  # waits for it (a sleeping process: cheap; the client is held, not sent away to come back at
  # once); a slot more than 10 s away is not taken and the request is answered 503. One client
  # flooding so waits behind its own requests, and takes at most its own rate of the server's.
  # A stream's parts are paced the same way, each as one request.
  defp pace(conf) do
    rate = conf.limits.max_client_rate

    with :ok <- Clients.pace(conf.client_pace, rate, conf.limits.max_wait, rate) do
      Clients.pace(conf.pace, conf.limits.max_rate, conf.limits.max_wait)
    end
  end

  defp authorized(socket, request, buffer, conf) do
    case Handler.authorize(request, conf.settings) do
      :ok ->
        case body_length(request, conf.limits) do
          {:ok, length} ->
            case read_body(socket, length, buffer, now() + conf.limits.body_timeout) do
              {:ok, body, rest} -> {:keep, handle(Map.put(request, :body, body), conf), rest}
              {:error, _} -> {:close, {408, "text/plain", "request body too slow"}}
            end

          {:error, response} ->
            {:close, response}
        end

      {:deny, response} ->
        {:close, response}
    end
  end

  defp handle(request, conf) do
    Handler.handle(request, conf.settings)
  end

  defp body_length(%{headers: headers}, limits) do
    cond do
      Map.has_key?(headers, "transfer-encoding") ->
        {:error, {411, "text/plain", "a body needs a Content-Length"}}

      length = headers["content-length"] ->
        case Integer.parse(String.trim(length)) do
          {n, ""} when n >= 0 and n <= limits.max_body ->
            {:ok, n}

          {n, ""} when n > limits.max_body ->
            {:error, {413, "text/plain", "request body larger than #{limits.max_body} bytes"}}

          _ ->
            {:error, {400, "text/plain", "bad Content-Length"}}
        end

      true ->
        {:ok, 0}
    end
  end

  # The body: what of it came with the head is in `buffer`, the rest is read from the socket.
  # Answers the bytes after it too (the next request, when the client pipelines).
  defp read_body(_socket, length, buffer, _deadline) when byte_size(buffer) >= length do
    <<body::binary-size(length), rest::binary>> = buffer
    {:ok, body, rest}
  end

  defp read_body(socket, length, buffer, deadline) do
    case :socket.recv(socket, length - byte_size(buffer), max(deadline - now(), 0)) do
      {:ok, more} -> {:ok, buffer <> more, ""}
      {:error, _} = error -> error
    end
  end

  defp keep_alive?(%{version: version, headers: headers}) do
    connection = String.downcase(headers["connection"] || "")

    case version do
      {1, 1} -> not String.contains?(connection, "close")
      _ -> String.contains?(connection, "keep-alive")
    end
  end

  defp respond(socket, response, keep, conf, request) do
    {status, type, body, extra} =
      case response do
        {status, type, body} -> {status, type, body, []}
        {_, _, _, _} = full -> full
      end

    body = IO.iodata_to_binary(body)
    sent = if request && request.method == "HEAD", do: "", else: body

    head = [
      "HTTP/1.1 ",
      Integer.to_string(status),
      " ",
      reason(status),
      "\r\ncontent-type: ",
      type,
      "\r\ncontent-length: ",
      Integer.to_string(byte_size(body)),
      "\r\ncache-control: no-store\r\nx-content-type-options: nosniff\r\nconnection: ",
      if(keep, do: "keep-alive", else: "close"),
      "\r\n",
      Enum.map(extra, fn {k, v} -> [k, ": ", v, "\r\n"] end),
      "\r\n"
    ]

    if request do
      Vws.Telemetry.execute(
        [:vws, :web, :request],
        %{duration: System.monotonic_time() - request[:started], bytes: byte_size(sent)},
        %{method: request.method, path: request.path, status: status, port: conf.settings.port}
      )
    end

    send_all(socket, [head, sent], conf)
  end

  # An answer the client does not read within `send_timeout` fails the send, and the connection
  # is closed by its caller.
  defp send_all(socket, data, conf) do
    case :socket.send(socket, data, conf.limits.send_timeout) do
      :ok -> :ok
      {:error, {reason, _rest}} -> {:error, reason}
      {:error, _} = error -> error
    end
  end

  # A stream runs in a process of its own, linked, while this one — the socket's owner — watches
  # the socket (a read that waits for data without blocking: `:nowait`, then the socket's
  # `select` message): when the client closes it or resets it, the stream is killed at once,
  # whatever it is waiting for (the next `interval`, new observations), and the socket closed; no
  # connection is left in CLOSE-WAIT until the stream's next write. What the client sends
  # meanwhile is read and dropped, up to `max_head` bytes in all, then the stream ends.
  defp watch_stream(socket, stream, conf, request) do
    pid = spawn_link(fn -> stream(socket, stream, conf, request) end)
    ref = Process.monitor(pid)
    watch(socket, pid, ref, conf.limits.max_head)
  end

  defp watch(socket, pid, ref, left) do
    case :socket.recv(socket, 0, :nowait) do
      {:ok, data} when byte_size(data) < left ->
        watch(socket, pid, ref, left - byte_size(data))

      {:select, info} ->
        handle = select_handle(info)

        receive do
          {:DOWN, ^ref, :process, ^pid, _} ->
            :socket.close(socket)

          {:"$socket", ^socket, :select, ^handle} ->
            watch(socket, pid, ref, left)

          {:"$socket", ^socket, :abort, {^handle, _reason}} ->
            end_stream(socket, pid)
        end

      # too much sent, closed or reset
      _ ->
        end_stream(socket, pid)
    end
  end

  defp select_handle({:select_info, _tag, handle}), do: handle
  defp select_handle({{:select_info, _tag, handle}, _data}), do: handle

  defp end_stream(socket, pid) do
    Process.unlink(pid)
    Process.exit(pid, :kill)
    :socket.close(socket)
  end

  # A stream (MTConnect `interval=`): `multipart/x-mixed-replace` in HTTP/1.1 chunks, one part
  # per document, until the client goes away (a send fails) or `more` says `:done`. Each part
  # after the first is paced as a request (pace/1).
  defp stream(socket, {:stream, type, first, more}, conf, request) do
    Process.flag(:priority, :low)

    boundary = Base.encode16(:rand.bytes(16), case: :lower)

    head = [
      "HTTP/1.1 200 OK\r\ncontent-type: multipart/x-mixed-replace;boundary=",
      boundary,
      "\r\ntransfer-encoding: chunked\r\ncache-control: no-store\r\n",
      "x-content-type-options: nosniff\r\nconnection: close\r\n\r\n"
    ]

    Vws.Telemetry.execute(
      [:vws, :web, :request],
      %{duration: System.monotonic_time() - request[:started], bytes: 0},
      %{method: request.method, path: request.path, status: 200, port: conf.settings.port}
    )

    part = fn doc ->
      doc = IO.iodata_to_binary(doc)

      data = [
        "--",
        boundary,
        "\r\ncontent-type: ",
        type,
        "\r\ncontent-length: ",
        Integer.to_string(byte_size(doc)),
        "\r\n\r\n",
        doc,
        "\r\n"
      ]

      size = IO.iodata_length(data)
      send_all(socket, [Integer.to_string(size, 16), "\r\n", data, "\r\n"], conf)
    end

    paced = fn doc ->
      with :ok <- pace(conf), do: part.(doc)
    end

    with :ok <- send_all(socket, head, conf), :ok <- part.(first) do
      result = more.(paced)
      _ = send_all(socket, "0\r\n\r\n", conf)
      result
    end
  end

  # Closes a connection whose request (or body) was not read to its end without resetting it
  # under the answer (a close with unread bytes resets the connection, and the client may lose
  # the answer): the write side is shut first, then whatever the client still sends is read and
  # dropped — never kept — for at most a second and 16 MB, then the socket is closed.
  defp close_unread(socket) do
    _ = :socket.shutdown(socket, :write)
    drain(socket, now() + 1_000, 16 * 1024 * 1024)
    :socket.close(socket)
  end

  defp drain(socket, deadline, left) when left > 0 do
    case :socket.recv(socket, 0, max(deadline - now(), 0)) do
      {:ok, data} -> drain(socket, deadline, left - byte_size(data))
      {:error, _} -> :ok
    end
  end

  defp drain(_socket, _deadline, _left), do: :ok

  defp recv(socket, deadline) do
    case deadline - now() do
      left when left > 0 -> :socket.recv(socket, 0, left)
      _ -> {:error, :timeout}
    end
  end

  defp now, do: System.monotonic_time(:millisecond)

  defp reason(200), do: "OK"
  defp reason(400), do: "Bad Request"
  defp reason(401), do: "Unauthorized"
  defp reason(403), do: "Forbidden"
  defp reason(404), do: "Not Found"
  defp reason(405), do: "Method Not Allowed"
  defp reason(408), do: "Request Timeout"
  defp reason(411), do: "Length Required"
  defp reason(413), do: "Content Too Large"
  defp reason(414), do: "URI Too Long"
  defp reason(431), do: "Request Header Fields Too Large"
  defp reason(500), do: "Internal Server Error"
  defp reason(503), do: "Service Unavailable"
  defp reason(_), do: "Status"
end
