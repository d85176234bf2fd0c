defmodule Vws.Ops.Web.Conn do
  @moduledoc false
  # One HTTP connection of `Vws.Ops.Web.Server`, in a process of its own: reads each request's head
  # (the socket parses it, `packet: :http_bin`) within its deadline, asks the handler whether the
  # request is allowed, reads the body only then, answers, and keeps the connection alive while
  # the client wants it and the limits allow. See `Vws.Ops.Web.Server` for the limits.

  alias Vws.Ops.Web.Handler

  @doc false
  def serve(socket, conf) do
    Process.flag(:priority, :low)
    loop(socket, conf, 1, conf.limits.head_timeout)
  end

  @doc false
  # The connection limit is reached: say so and close, without reading anything.
  def refuse_busy(socket, conf) do
    _ = respond(socket, {503, "text/plain", "busy: too many connections"}, false, conf, nil)
    :gen_tcp.close(socket)
  end

  defp loop(socket, conf, n, wait) do
    deadline = now() + wait

    case read_head(socket, conf.limits, deadline) do
      {:ok, request} ->
        case answer(socket, request, conf) do
          {:keep, {:stream, _type, _first, _more} = stream} ->
            _ = stream(socket, stream, conf, request)
            :gen_tcp.close(socket)

          {:keep, response} ->
            keep = n < conf.limits.max_requests and keep_alive?(request)

            case respond(socket, response, keep, conf, request) do
              :ok when keep -> loop(socket, conf, n + 1, conf.limits.idle_timeout)
              _ -> :gen_tcp.close(socket)
            end

          {:close, response} ->
            _ = respond(socket, response, false, conf, request)
            close_unread(socket)
        end

      {:error, {status, why}} ->
        _ = respond(socket, {status, "text/plain", why}, false, conf, nil)
        close_unread(socket)

      {:error, _closed_or_timeout} ->
        :gen_tcp.close(socket)
    end
  end

  ## The head

  defp read_head(socket, limits, deadline) do
    with {:ok, {:http_request, method, uri, version}} <- recv(socket, deadline),
         {:ok, path, query} <- target(uri),
         {:ok, headers} <- read_headers(socket, limits, deadline, %{}, 0, 0) do
      {:ok,
       %{
         method: method_name(method),
         started: System.monotonic_time(),
         path: path,
         query: query,
         version: version,
         headers: headers
       }}
    else
      {:ok, {:http_error, _}} -> {:error, {400, "bad request line"}}
      {:ok, _other} -> {:error, {400, "bad request"}}
      {:error, :bad_target} -> {:error, {400, "bad request target"}}
      {:error, _} = error -> error
    end
  end

  defp read_headers(socket, limits, deadline, acc, count, bytes) do
    case recv(socket, deadline) do
      {:ok, :http_eoh} ->
        {:ok, acc}

      {:ok, {:http_header, _, name, _, value}} ->
        count = count + 1
        name = header_name(name)
        bytes = bytes + byte_size(name) + byte_size(value)

        if count > limits.max_headers or bytes > limits.max_head do
          {:error, {431, "request header fields too large"}}
        else
          acc = Map.update(acc, name, value, &(&1 <> ", " <> value))
          read_headers(socket, limits, deadline, acc, count, bytes)
        end

      {:ok, {:http_error, _}} ->
        {:error, {400, "bad header line"}}

      {:error, _} = error ->
        error
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
  defp answer(socket, request, conf) do
    case pace(conf) do
      :ok -> authorized(socket, request, conf)
      :busy -> {:close, {503, "text/plain", "busy: too many requests"}}
    end
  end

  # The server-wide request rate: each request takes the next free slot (1/max_rate s apart)
  # and waits for it (a sleeping process: cheap; the client is held, not sent away to come back
  # at once); a slot more than 10 s away is not taken.
  defp pace(%{pace: ref, limits: %{max_rate: rate}}) do
    interval = div(1_000_000, rate)
    now = System.monotonic_time(:microsecond)
    next = :atomics.get(ref, 1)
    slot = max(next, now)

    cond do
      slot - now > 10_000_000 ->
        :busy

      :atomics.compare_exchange(ref, 1, next, slot + interval) == :ok ->
        wait = div(slot - now, 1000)
        if wait > 0, do: Process.sleep(wait)
        :ok

      true ->
        pace(%{pace: ref, limits: %{max_rate: rate}})
    end
  end

  defp authorized(socket, request, conf) do
    case Handler.authorize(request, conf.settings) do
      :ok ->
        case body_length(request, conf.limits) do
          {:ok, 0} ->
            {:keep, handle(Map.put(request, :body, ""), conf)}

          {:ok, length} ->
            case read_body(socket, length, now() + conf.limits.body_timeout) do
              {:ok, body} -> {:keep, handle(Map.put(request, :body, body), conf)}
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

  defp read_body(socket, length, deadline) do
    :ok = :inet.setopts(socket, packet: :raw)

    result =
      case :gen_tcp.recv(socket, length, max(deadline - now(), 0)) do
        {:ok, body} -> {:ok, body}
        {:error, _} = error -> error
      end

    _ = :inet.setopts(socket, packet: :http_bin)
    result
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

    :gen_tcp.send(socket, [head, sent])
  end

  # A stream (MTConnect `interval=`): `multipart/x-mixed-replace` in HTTP/1.1 chunks, one part
  # per document, until the client goes away (a send fails) or `more` says `:done`.
  defp stream(socket, {:stream, type, first, more}, conf, request) do
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
      :gen_tcp.send(socket, [Integer.to_string(size, 16), "\r\n", data, "\r\n"])
    end

    with :ok <- :gen_tcp.send(socket, head), :ok <- part.(first) do
      result = more.(part)
      _ = :gen_tcp.send(socket, "0\r\n\r\n")
      result
    end
  end

  # Closes a connection whose request (or body) was not read to its end without resetting it
  # under the answer (a close with unread bytes resets the connection, and the client may lose
  # the answer): the write side is shut first, then whatever the client still sends is read and
  # dropped — never kept — for at most a second and 16 MB, then the socket is closed.
  defp close_unread(socket) do
    _ = :gen_tcp.shutdown(socket, :write)
    _ = :inet.setopts(socket, packet: :raw)
    drain(socket, now() + 1_000, 16 * 1024 * 1024)
    :gen_tcp.close(socket)
  end

  defp drain(socket, deadline, left) when left > 0 do
    case :gen_tcp.recv(socket, 0, max(deadline - now(), 0)) do
      {:ok, data} -> drain(socket, deadline, left - byte_size(data))
      {:error, _} -> :ok
    end
  end

  defp drain(_socket, _deadline, _left), do: :ok

  defp recv(socket, deadline) do
    case deadline - now() do
      left when left > 0 -> :gen_tcp.recv(socket, 0, left)
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
  defp reason(431), do: "Request Header Fields Too Large"
  defp reason(500), do: "Internal Server Error"
  defp reason(503), do: "Service Unavailable"
  defp reason(_), do: "Status"
end
