defmodule Vws.Test.MTCClient do
  @moduledoc """
  An MTConnect client for the tests and `bench/mtconnect_soak.exs`, over real TCP:

    * `get/3` — one request: `{status, content_type, body}`;
    * `stream/3` — a streaming request (`interval=`): a process that reads the
      `multipart/x-mixed-replace` answer — HTTP/1.1 chunks, then parts by their boundary and
      `content-length`, never assuming one part per chunk — and sends the owner
      `{:mtc_part, ref, document}` for each part and `{:mtc_closed, ref}` at the end;
    * `observations/1`, `header/2` — what a streams document says.
  """

  @doc "GET `path` on 127.0.0.1:`port`: `{status, content_type, body}`."
  def get(port, path, headers \\ []) do
    {:ok, socket} = :gen_tcp.connect(~c"127.0.0.1", port, [:binary, active: false], 10_000)

    :ok =
      :gen_tcp.send(socket, [
        "GET ",
        path,
        " HTTP/1.1\r\nhost: 127.0.0.1\r\nconnection: close\r\n",
        Enum.map(headers, fn {k, v} -> [k, ": ", v, "\r\n"] end),
        "\r\n"
      ])

    data = read_all(socket, "")
    {head, body} = split_head(data)
    {status, hs} = parse_head(head)
    {status, hs["content-type"], body}
  end

  defp read_all(socket, acc) do
    case :gen_tcp.recv(socket, 0, 30_000) do
      {:ok, data} -> read_all(socket, acc <> data)
      {:error, :closed} -> acc
    end
  end

  defp split_head(data) do
    [head, body] = :binary.split(data, "\r\n\r\n")
    {head, body}
  end

  defp parse_head(head) do
    [status_line | lines] = String.split(head, "\r\n")
    ["HTTP/1.1", status | _] = String.split(status_line, " ")

    hs =
      for line <- lines, [k, v] = String.split(line, ":", parts: 2), into: %{} do
        {String.downcase(k), String.trim(v)}
      end

    {String.to_integer(status), hs}
  end

  @doc """
  Starts a streaming request; returns `{ref, pid, head}` once the answer's head is read (`head`:
  `%{status, headers}`). The reader is linked to the caller; `stop/1` ends it.
  """
  def stream(port, path, headers \\ []) do
    owner = self()
    ref = make_ref()

    pid =
      spawn_link(fn ->
        {:ok, socket} = :gen_tcp.connect(~c"127.0.0.1", port, [:binary, active: false], 10_000)

        :ok =
          :gen_tcp.send(socket, [
            "GET ",
            path,
            " HTTP/1.1\r\nhost: 127.0.0.1\r\n",
            Enum.map(headers, fn {k, v} -> [k, ": ", v, "\r\n"] end),
            "\r\n"
          ])

        {head, rest} = read_head(socket, "")
        {status, hs} = parse_head(head)
        send(owner, {:mtc_head, ref, %{status: status, headers: hs}})

        boundary =
          case Regex.run(~r/boundary=([^;\s]+)/, hs["content-type"] || "") do
            [_, b] -> b
            nil -> nil
          end

        if status == 200 and boundary do
          chunks(socket, rest, "", boundary, owner, ref)
        else
          send(owner, {:mtc_body, ref, rest <> read_all(socket, "")})
        end

        send(owner, {:mtc_closed, ref})
      end)

    receive do
      {:mtc_head, ^ref, head} -> {ref, pid, head}
    after
      30_000 -> raise "no answer head within 30 s"
    end
  end

  @doc "Ends a stream reader."
  def stop(pid) do
    Process.unlink(pid)
    Process.exit(pid, :kill)
  end

  defp read_head(socket, acc) do
    case :binary.split(acc, "\r\n\r\n") do
      [head, rest] ->
        {head, rest}

      [_] ->
        {:ok, data} = :gen_tcp.recv(socket, 0, 30_000)
        read_head(socket, acc <> data)
    end
  end

  # HTTP/1.1 chunks: `raw` is what is read and not yet decoded, `body` the decoded bytes not
  # yet made into parts
  defp chunks(socket, raw, body, boundary, owner, ref) do
    case decode_chunk(raw) do
      {:chunk, "", _rest} ->
        :ok

      {:chunk, data, rest} ->
        body = parts(body <> data, boundary, owner, ref)
        chunks(socket, rest, body, boundary, owner, ref)

      :more ->
        case :gen_tcp.recv(socket, 0, 120_000) do
          {:ok, data} -> chunks(socket, raw <> data, body, boundary, owner, ref)
          {:error, _} -> :ok
        end
    end
  end

  defp decode_chunk(raw) do
    with [size_line, rest] <- :binary.split(raw, "\r\n"),
         {size, _} <- Integer.parse(size_line, 16),
         true <- byte_size(rest) >= size + 2 do
      <<data::binary-size(size), "\r\n", rest::binary>> = rest
      {:chunk, data, rest}
    else
      _ -> :more
    end
  end

  defp parts(body, boundary, owner, ref) do
    marker = "--" <> boundary <> "\r\n"

    with true <- String.starts_with?(body, marker),
         rest = binary_part(body, byte_size(marker), byte_size(body) - byte_size(marker)),
         [head, after_head] <- :binary.split(rest, "\r\n\r\n"),
         [_, len] <- Regex.run(~r/content-length:\s*(\d+)/i, head),
         len = String.to_integer(len),
         true <- byte_size(after_head) >= len + 2 do
      <<doc::binary-size(len), "\r\n", more::binary>> = after_head
      send(owner, {:mtc_part, ref, doc})
      parts(more, boundary, owner, ref)
    else
      _ -> body
    end
  end

  @doc "`[{element, dataItemId, sequence, value}]` of the observations of a streams document."
  def observations(text) do
    ~r{<(\w+) dataItemId="([^"]+)" timestamp="[^"]+" sequence="(\d+)"[^>]*?(?:/>|>([^<]*)</\1>)}
    |> Regex.scan(text, capture: :all_but_first)
    |> Enum.map(fn
      [el, id, seq] -> {el, id, String.to_integer(seq), ""}
      [el, id, seq, value] -> {el, id, String.to_integer(seq), value}
    end)
  end

  @doc "A numeric attribute of a document's Header."
  def header(text, attr) do
    [_, n] = Regex.run(~r{<Header [^>]*\b#{attr}="(\d+)"}, text)
    String.to_integer(n)
  end
end
