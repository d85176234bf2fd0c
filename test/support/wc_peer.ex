defmodule Vws.Test.WCPeer do
  @moduledoc """
  A bare workstation-controller end for tests: connects to SUN_COMM over any transport, sends raw
  lines and collects the lines that come back, so tests see exactly the bytes on the wire.
  """
  use GenServer

  alias Vws.Codecs.WC.Reply

  alias Vws.Links.Transport
  alias Vws.Codecs.WC.{CommandString, LineDecoder}

  def connect(endpoint, opts \\ []) do
    GenServer.start_link(__MODULE__, {endpoint, opts})
  end

  @doc "Sends `line` followed by CR LF."
  def send_line(peer, line), do: GenServer.call(peer, {:send, [line, "\r\n"]})

  @doc "Sends raw bytes."
  def send_raw(peer, bytes), do: GenServer.call(peer, {:send, bytes})

  @doc "Encodes and sends a command string built from `{letter, number, text}` tuples."
  def send_string(peer, seq, commands, opts \\ []) do
    line = string(seq, commands, opts)
    :ok = send_raw(peer, line)
    line
  end

  @doc "The encoded command string (with CR LF)."
  def string(seq, commands, opts \\ []) do
    cmds =
      for {letter, number, text} <- commands do
        %Vws.Codecs.WC.Command{
          letter: letter,
          set: Vws.Codecs.WC.Command.set_for_letter(letter),
          number: number,
          text: text
        }
      end

    IO.iodata_to_binary(CommandString.encode(%CommandString{sequence: seq, commands: cmds}, opts))
  end

  @doc "The next line received (without CR LF), waiting up to `timeout` ms."
  def recv_line(peer, timeout \\ 5_000),
    do: GenServer.call(peer, {:recv, timeout}, timeout + 1_000)

  @doc "Sends a status command and returns the decoded `{number, text}` of the answer."
  def status(peer, seq, number, name, opts \\ []) do
    send_string(peer, seq, [{"S", number, name}], opts)
    line = recv_line(peer)
    {:ok, {:status, ^number, text}} = Vws.Codecs.WC.Reply.decode(line, opts)
    text
  end

  @doc "Polls a status command until `fun.(text)` is true or `timeout` ms pass; returns the last text."
  def await_status(peer, number, name, fun, timeout \\ 5_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    do_await(peer, number, name, fun, deadline)
  end

  defp do_await(peer, number, name, fun, deadline) do
    text = status(peer, rem(System.unique_integer([:positive]), 10_000), number, name)

    cond do
      fun.(text) -> text
      System.monotonic_time(:millisecond) > deadline -> text
      true -> Process.sleep(10) && do_await(peer, number, name, fun, deadline)
    end
  end

  @doc """
  Sends the Monarch command `text` as command `number` in a string of its own, and polls
  `MONARCH_CMD` until it is no longer EXECUTING (within `timeout` ms): its status without the
  command's number (`"DONE"`, `"ERROR …"`).
  """
  def monarch(peer, number, text, timeout \\ 60_000) do
    seq = fn -> rem(System.unique_integer([:positive]), 10_000) end
    s = seq.()
    send_string(peer, s, [{"M", number, text}])
    {:ok, {:ack, ^s}} = Vws.Codecs.WC.Reply.decode(recv_line(peer))

    <<_number::binary-4, status::binary>> =
      await_status(peer, seq.(), "MONARCH_CMD", &(not (&1 =~ "EXECUTING")), timeout)

    status
  end

  def close(peer), do: GenServer.stop(peer)

  @doc """
  The answer SUN_COMM gives to line `n` (1-based) of a downloaded program `lines` when it stores
  it: `{:line_ack, n}`, and for the closing `%` `{:line_ack, n, crc}`, the CRC of the whole
  program (PROTOCOLS.md §1 "Whole-program check").
  """
  def download_answer(lines, n) do
    if n == length(lines),
      do: {:line_ack, rem(n, 10_000), Vws.Codecs.WC.ProgramCRC.compute(lines)},
      else: {:line_ack, rem(n, 10_000)}
  end

  @doc """
  Whether the text of an UPLOAD_SUN line, after the lines `received` so far (newest first), ends
  the program: `{:closing, lines}` — its closing `%/cccc`, the CRC checked (it raises when the
  CRC is not the program's) — or `:more`.
  """
  def upload_closing(text, received) do
    case Vws.Codecs.WC.ProgramCRC.split_closing(text) do
      {:ok, last, crc} when received != [] ->
        if String.trim(last) == "%" do
          lines = Enum.reverse([last | received])
          ours = Vws.Codecs.WC.ProgramCRC.compute(lines)
          crc == ours || raise "UPLOAD_SUN closing CRC #{crc}, the program's is #{ours}"
          {:closing, lines}
        else
          :more
        end

      _ ->
        :more
    end
  end

  @doc """
  The lines of an UPLOAD_SUN, each answered `A nnnn`, until its closing `%/cccc`
  (`upload_closing/2`): the program as stored.
  """
  def upload_lines(peer, received \\ []) do
    n = rem(length(received) + 1, 10_000)
    {:ok, {:line, ^n, line}} = Reply.decode_line(recv_line(peer))
    send_raw(peer, Reply.encode({:line_ack, n}))

    case upload_closing(line, received) do
      {:closing, lines} -> lines
      :more -> upload_lines(peer, [line | received])
    end
  end

  @impl true
  def init({endpoint, opts}) do
    case connect_retrying(endpoint, Keyword.get(opts, :connect_timeout, 5_000)) do
      {:ok, conn} ->
        :ok = Transport.activate(conn)

        {:ok,
         %{
           conn: conn,
           decoder: LineDecoder.new(max_line: 1_000_000),
           lines: :queue.new(),
           waiting: nil,
           closed: false
         }}

      {:error, reason} ->
        {:stop, reason}
    end
  end

  defp connect_retrying(endpoint, timeout) do
    deadline = System.monotonic_time(:millisecond) + timeout

    Stream.repeatedly(fn -> Vws.CEC.Cell.connect(endpoint) end)
    |> Enum.reduce_while(nil, fn
      {:ok, conn}, _ ->
        {:halt, {:ok, conn}}

      error, _ ->
        if System.monotonic_time(:millisecond) > deadline,
          do: {:halt, error},
          else: Process.sleep(20) && {:cont, error}
    end)
  end

  @impl true
  def handle_call({:send, bytes}, _from, s), do: {:reply, Transport.send(s.conn, bytes), s}

  def handle_call({:recv, timeout}, from, s) do
    case :queue.out(s.lines) do
      {{:value, line}, rest} ->
        {:reply, line, %{s | lines: rest}}

      {:empty, _} ->
        ref = Process.send_after(self(), {:recv_timeout, from}, timeout)
        {:noreply, %{s | waiting: {from, ref}}}
    end
  end

  @impl true
  def handle_info({:recv_timeout, from}, %{waiting: {from, _}} = s) do
    GenServer.reply(from, {:timeout, if(s.closed, do: :closed, else: :open)})
    {:noreply, %{s | waiting: nil}}
  end

  def handle_info({:recv_timeout, _}, s), do: {:noreply, s}

  def handle_info(msg, s) do
    case Transport.handle_message(s.conn, msg) do
      {:data, bytes} ->
        {lines, decoder} = LineDecoder.feed(s.decoder, bytes)
        Transport.activate(s.conn)
        {:noreply, Enum.reduce(lines, %{s | decoder: decoder}, &deliver/2)}

      :closed ->
        {:noreply, %{s | closed: true}}

      _ ->
        {:noreply, s}
    end
  end

  defp deliver(line, %{waiting: {from, ref}} = s) do
    Process.cancel_timer(ref)
    GenServer.reply(from, line)
    %{s | waiting: nil}
  end

  defp deliver(line, s), do: %{s | lines: :queue.in(line, s.lines)}
end
