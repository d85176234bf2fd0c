defmodule Vws.Test.DNCPeer do
  @moduledoc """
  A bare DNC Level 2 end for tests: takes a connection from a listener (or connects), sends raw
  bytes and hands back exactly the bytes the link under test sent, so a test scripts the line
  byte by byte.
  """
  use GenServer

  alias Vws.Links.Transport

  @doc "Accepts the next connection on `listener` (waiting up to `timeout` ms)."
  def accept(listener, timeout \\ 5_000),
    do: GenServer.start_link(__MODULE__, {:accept, listener, timeout})

  @doc "Connects to `endpoint`."
  def connect(endpoint), do: GenServer.start_link(__MODULE__, {:connect, endpoint})

  @doc "Sends raw bytes (iodata)."
  def send_raw(peer, bytes), do: GenServer.call(peer, {:send, bytes})

  @doc "The next `n` bytes received, or `{:timeout, bytes_so_far}` after `timeout` ms."
  def recv(peer, n, timeout \\ 5_000),
    do: GenServer.call(peer, {:recv, n, timeout}, timeout + 1_000)

  @doc "True when nothing at all arrives for `ms` ms (what arrives stays queued)."
  def quiet?(peer, ms), do: GenServer.call(peer, {:quiet, ms}, ms + 1_000)

  @doc "Everything received and not yet taken."
  def drain(peer), do: GenServer.call(peer, :drain)

  def close(peer), do: GenServer.stop(peer)

  @impl true
  def init({:accept, listener, timeout}) do
    with {:ok, conn} <- Transport.accept(listener, timeout), do: ready(conn)
  end

  def init({:connect, endpoint}) do
    with {:ok, conn} <- Transport.connect(endpoint), do: ready(conn)
  end

  defp ready(conn) do
    :ok = Transport.activate(conn)
    {:ok, %{conn: conn, buffer: <<>>, waiting: nil, closed: false}}
  end

  @impl true
  def handle_call({:send, bytes}, _from, s), do: {:reply, Transport.send(s.conn, bytes), s}

  def handle_call({:recv, n, timeout}, from, s) do
    ref = Process.send_after(self(), {:recv_timeout, from}, timeout)
    {:noreply, deliver(%{s | waiting: {:recv, from, n, ref}})}
  end

  def handle_call({:quiet, ms}, from, s) do
    if s.buffer != <<>> do
      {:reply, false, s}
    else
      ref = Process.send_after(self(), {:quiet_over, from}, ms)
      {:noreply, %{s | waiting: {:quiet, from, ref}}}
    end
  end

  def handle_call(:drain, _from, s), do: {:reply, s.buffer, %{s | buffer: <<>>}}

  @impl true
  def handle_info({:recv_timeout, from}, %{waiting: {:recv, from, _, _}} = s) do
    GenServer.reply(from, {:timeout, s.buffer})
    {:noreply, %{s | waiting: nil}}
  end

  def handle_info({:quiet_over, from}, %{waiting: {:quiet, from, _}} = s) do
    GenServer.reply(from, true)
    {:noreply, %{s | waiting: nil}}
  end

  def handle_info({tag, _from}, s) when tag in [:recv_timeout, :quiet_over], do: {:noreply, s}

  def handle_info(msg, s) do
    case Transport.handle_message(s.conn, msg) do
      {:data, bytes} ->
        Transport.activate(s.conn)
        {:noreply, deliver(%{s | buffer: s.buffer <> bytes})}

      :closed ->
        {:noreply, %{s | closed: true}}

      _ ->
        {:noreply, s}
    end
  end

  defp deliver(%{waiting: {:recv, from, n, ref}, buffer: buffer} = s)
       when byte_size(buffer) >= n do
    Process.cancel_timer(ref)
    <<bytes::binary-size(n), rest::binary>> = buffer
    GenServer.reply(from, bytes)
    %{s | waiting: nil, buffer: rest}
  end

  defp deliver(%{waiting: {:quiet, from, ref}, buffer: buffer} = s) when buffer != <<>> do
    Process.cancel_timer(ref)
    GenServer.reply(from, false)
    %{s | waiting: nil}
  end

  defp deliver(s), do: s
end
