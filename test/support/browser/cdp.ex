defmodule Vws.Test.Browser.CDP do
  @moduledoc """
  One headless Chromium for the whole test run, driven over the DevTools protocol (a WebSocket on
  loopback): each page is a new tab, read when it has drawn what the test waits for, then closed.
  Starting Chromium for every read (`--dump-dom`) cost about a second of both cores each time,
  some thirty times in the dashboard tests, which run alone (not async).

  Started on first use, not linked to any test; Chromium stops when this VM does (its wrapper
  shell kills it when its standard input, held by this process's port, closes). Requests are
  served one at a time.
  """
  use GenServer

  alias Vws.Ops.Web.JSON
  alias Vws.Test.JSONDecode

  @name __MODULE__

  @doc """
  Opens `url` in a new tab, waits until the JavaScript expression `until` is true (polled every
  50 ms; `timeout` ms at most, then fails with the page's text so far), and reads it: `:dom` (the
  DOM as HTML) or `{:screenshot, width, height}` (PNG bytes of the whole page at that size). The
  tab is closed after.
  """
  def read(url, until, timeout, what) do
    case GenServer.call(server(), {:read, url, until, timeout, what}, timeout + 30_000) do
      {:ok, result} -> result
      {:error, message} -> raise ExUnit.AssertionError, message: message
    end
  end

  defp server do
    case GenServer.start(__MODULE__, [], name: @name) do
      {:ok, pid} -> pid
      {:error, {:already_started, pid}} -> pid
    end
  end

  @impl true
  def init([]) do
    profile = Path.join(System.tmp_dir!(), "vws-cdp-#{System.unique_integer([:positive])}")
    File.mkdir_p!(profile)

    args =
      Vws.Test.Browser.headless(profile) ++
        ["--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0", "about:blank"]

    # Chromium in the background; the shell waits on its own standard input (this port) and
    # stops Chromium when it closes: when this process or the VM ends
    script = ~s("$@" >/dev/null 2>&1 & pid=$!; read _; kill $pid 2>/dev/null; wait $pid)

    port =
      Port.open({:spawn_executable, "/bin/sh"}, [
        :binary,
        args: ["-c", script, "sh", Vws.Test.Browser.chromium() | args]
      ])

    {port_number, path} = devtools_address(profile, 300)
    {:ok, socket} = :gen_tcp.connect({127, 0, 0, 1}, port_number, [:binary, active: false])
    buffer = handshake(socket, path)
    {:ok, %{port: port, socket: socket, buffer: buffer, id: 0, profile: profile}}
  end

  # Chromium writes its DevTools port and the browser's path into the profile when it listens
  defp devtools_address(_profile, 0), do: raise("Chromium did not open its DevTools port")

  defp devtools_address(profile, tries) do
    with {:ok, text} <- File.read(Path.join(profile, "DevToolsActivePort")),
         [port, path] <- String.split(text, "\n", trim: true) do
      {String.to_integer(port), path}
    else
      _ ->
        Process.sleep(100)
        devtools_address(profile, tries - 1)
    end
  end

  defp handshake(socket, path) do
    key = Base.encode64(:crypto.strong_rand_bytes(16))

    :ok =
      :gen_tcp.send(socket, [
        "GET #{path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n",
        "Connection: Upgrade\r\nSec-WebSocket-Key: #{key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
      ])

    read_head(socket, "")
  end

  defp read_head(socket, acc) do
    case :binary.split(acc, "\r\n\r\n") do
      ["HTTP/1.1 101" <> _, rest] ->
        rest

      [head, _] ->
        raise "Chromium refused the DevTools WebSocket: #{head}"

      [_] ->
        {:ok, data} = :gen_tcp.recv(socket, 0, 10_000)
        read_head(socket, acc <> data)
    end
  end

  @impl true
  def handle_call({:read, url, until, timeout, what}, _from, state) do
    {%{"targetId" => target}, state} = command(state, "Target.createTarget", %{url: url})

    {%{"sessionId" => session}, state} =
      command(state, "Target.attachToTarget", %{targetId: target, flatten: true})

    deadline = System.monotonic_time(:millisecond) + timeout

    {reply, state} =
      case await(state, session, until, deadline) do
        {:ok, state} ->
          {result, state} = take(state, session, what)
          {{:ok, result}, state}

        {:timeout, state} ->
          {text, state} = evaluate(state, session, "document.body ? document.body.innerText : ''")
          {{:error, "the page never showed #{until} in #{timeout} ms:\n#{text}"}, state}
      end

    {_, state} = command(state, "Target.closeTarget", %{targetId: target})
    {:reply, reply, state}
  end

  defp take(state, session, :dom),
    do: evaluate(state, session, "document.documentElement.outerHTML")

  defp take(state, session, {:screenshot, width, height}) do
    metrics = %{width: width, height: height, deviceScaleFactor: 1, mobile: false}
    {_, state} = command(state, "Emulation.setDeviceMetricsOverride", metrics, session)

    {%{"data" => png}, state} =
      command(state, "Page.captureScreenshot", %{format: "png"}, session)

    {Base.decode64!(png), state}
  end

  defp await(state, session, until, deadline) do
    # a new tab starts on about:blank (complete at once) and only then navigates to the page
    case evaluate(state, session, "document.URL !== 'about:blank' && Boolean(#{until})") do
      {true, state} ->
        {:ok, state}

      {_, state} ->
        if System.monotonic_time(:millisecond) > deadline do
          {:timeout, state}
        else
          Process.sleep(50)
          await(state, session, until, deadline)
        end
    end
  end

  defp evaluate(state, session, expression) do
    {result, state} =
      command(state, "Runtime.evaluate", %{expression: expression, returnByValue: true}, session)

    {get_in(result, ["result", "value"]), state}
  end

  defp command(state, method, params, session \\ nil) do
    id = state.id + 1
    message = %{id: id, method: method, params: params}
    message = if session, do: Map.put(message, :sessionId, session), else: message
    :ok = send_text(state.socket, JSON.encode_to_string(message))
    await_reply(%{state | id: id}, id, method)
  end

  defp await_reply(state, id, method) do
    {text, state} = read_message(state)

    case JSONDecode.decode(text) do
      %{"id" => ^id, "result" => result} -> {result, state}
      %{"id" => ^id, "error" => error} -> raise "DevTools #{method}: #{inspect(error)}"
      _event -> await_reply(state, id, method)
    end
  end

  ## WebSocket frames (RFC 6455): the client masks what it sends

  defp send_text(socket, payload) do
    mask = :crypto.strong_rand_bytes(4)
    size = byte_size(payload)

    length =
      cond do
        size < 126 -> <<1::1, size::7>>
        size < 65_536 -> <<1::1, 126::7, size::16>>
        true -> <<1::1, 127::7, size::64>>
      end

    :gen_tcp.send(socket, [<<1::1, 0::3, 1::4>>, length, mask, masked(payload, mask)])
  end

  defp masked(payload, <<m::32>>) do
    whole = div(byte_size(payload), 4) * 4
    <<head::binary-size(whole), tail::binary>> = payload
    words = for <<w::32 <- head>>, into: <<>>, do: <<Bitwise.bxor(w, m)::32>>
    <<mask_bytes::binary-size(byte_size(tail)), _::binary>> = <<m::32>>
    tail = :crypto.exor(tail, mask_bytes)
    words <> tail
  end

  # a whole message: frames until FIN, control frames answered or skipped
  defp read_message(state, acc \\ []) do
    {<<fin::1, _::3, opcode::4, 0::1, len7::7>>, state} = read_exact(state, 2)

    {size, state} =
      case len7 do
        126 -> with {<<n::16>>, s} <- read_exact(state, 2), do: {n, s}
        127 -> with {<<n::64>>, s} <- read_exact(state, 8), do: {n, s}
        n -> {n, state}
      end

    {payload, state} = read_exact(state, size)

    case {opcode, fin} do
      {9, _} ->
        :ok = :gen_tcp.send(state.socket, [<<1::1, 0::3, 10::4>>, <<1::1, 0::7>>, <<0::32>>])
        read_message(state, acc)

      {10, _} ->
        read_message(state, acc)

      {8, _} ->
        raise "Chromium closed the DevTools WebSocket"

      {_, 1} ->
        {IO.iodata_to_binary(Enum.reverse([payload | acc])), state}

      {_, 0} ->
        read_message(state, [payload | acc])
    end
  end

  defp read_exact(%{buffer: buffer} = state, n) when byte_size(buffer) >= n do
    <<wanted::binary-size(n), rest::binary>> = buffer
    {wanted, %{state | buffer: rest}}
  end

  defp read_exact(state, n) do
    {:ok, data} = :gen_tcp.recv(state.socket, 0, 60_000)
    read_exact(%{state | buffer: state.buffer <> data}, n)
  end
end
