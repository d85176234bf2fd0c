defmodule Vws.Test.VALPeer do
  @moduledoc """
  Plays the VAL II end of a `Vws.Links.VAL` wire in tests of the layers above DDCMP: real DDCMP frames
  on a loopback transport, run by a `Vws.Links.DDCMP.Protocol` of its own (no simulator behind it), the
  test deciding when the link comes up and how it goes down.

      {:ok, peer} = VALPeer.start_link()
      {:ok, val} = Vws.Links.VAL.start_link(ddcmp: [endpoint: VALPeer.endpoint(peer)])
      :ok = VALPeer.up(peer)

  Until `up/1`, and again from the moment the link went down or restarted, the peer is *held*:
  it answers nothing (the CEC's STRTs go unanswered), and `deliver/2` puts a data message on the
  line outside any session — one the CEC's link must ignore. `up/1` starts the link from the
  peer's side (STRT) and returns once it runs.

  The test receives `{:val_peer, peer, {:sent, binary}}` for every message the CEC sent and
  `{:val_peer, peer, :restart}` when the CEC restarted a running link (its STRT).
  """
  use GenServer

  alias Vws.Links.DDCMP.{Frame, Protocol}
  alias Vws.Links.Transport

  @never 600_000

  def start_link(opts \\ []), do: GenServer.start_link(__MODULE__, {self(), opts})

  @doc "The loopback endpoint the CEC dials."
  def endpoint(peer), do: GenServer.call(peer, :endpoint)

  @doc "Brings the link up (waiting for the CEC's connection first); returns once it runs."
  def up(peer), do: GenServer.call(peer, :up, 10_000)

  @doc "Sends a VAL message to the CEC (outside any session while held)."
  def deliver(peer, iodata), do: GenServer.call(peer, {:deliver, IO.iodata_to_binary(iodata)})

  @doc """
  Takes the link down: `:closed` closes the connection (the CEC dials again and is accepted,
  held); anything else NAKs the CEC `max_failures` times (default 8) so that its link gives up
  (`:too_many_failures`).
  """
  def down(peer, how), do: GenServer.call(peer, {:down, how, <<>>})

  @doc "Delivers a message and, in the same chunk of bytes, takes the link down as `down/2`."
  def deliver_and_down(peer, iodata, how),
    do: GenServer.call(peer, {:down, how, IO.iodata_to_binary(iodata)})

  @doc "Restarts the peer's side of a running link: a STRT the CEC sees as `:peer_restarted`."
  def peer_restarted(peer), do: GenServer.call(peer, :peer_restarted)

  @impl true
  def init({test, opts}) do
    endpoint = "loopback:val-peer-#{System.unique_integer([:positive])}"
    {:ok, listener} = Transport.listen(endpoint)
    Transport.start_acceptor(listener, self(), :accepted)

    {:ok,
     %{
       test: test,
       endpoint: endpoint,
       conn: nil,
       protocol: nil,
       held: true,
       waiting_up: nil,
       naks: Keyword.get(opts, :max_failures, 8)
     }}
  end

  @impl true
  def handle_call(:endpoint, _from, s), do: {:reply, s.endpoint, s}

  def handle_call(:up, from, %{conn: nil} = s), do: {:noreply, %{s | waiting_up: from}}
  def handle_call(:up, from, s), do: {:noreply, start_up(%{s | waiting_up: from})}

  def handle_call({:deliver, bytes}, _from, %{held: false} = s) do
    {:ok, protocol, frames, _events} = Protocol.send(s.protocol, bytes, hold: false)
    write(s, frames)
    {:reply, :ok, %{s | protocol: protocol}}
  end

  def handle_call({:deliver, bytes}, _from, s) do
    write(s, [Frame.data(1, 0, bytes)])
    {:reply, :ok, s}
  end

  def handle_call({:down, :closed, bytes}, _from, s) do
    if bytes != <<>>, do: write(s, data_frames(s, bytes))
    Transport.close(s.conn)
    {:reply, :ok, %{s | conn: nil, held: true}}
  end

  def handle_call({:down, _how, bytes}, _from, s) do
    # RESP = what the peer holds: within A..N of the CEC, so each NAK counts as a failure
    r = if s.protocol, do: Protocol.info(s.protocol).r, else: 0
    data = if bytes == <<>>, do: [], else: data_frames(s, bytes)
    write(s, data ++ List.duplicate(Frame.nak(:data_crc, r), s.naks))
    {:reply, :ok, %{s | held: true}}
  end

  def handle_call(:peer_restarted, _from, s) do
    write(s, [Frame.strt()])
    {:reply, :ok, %{s | held: true}}
  end

  @impl true
  def handle_info({:accepted, conn}, s) do
    if s.conn, do: Transport.close(s.conn)
    :ok = Transport.activate(conn)
    s = %{s | conn: conn, held: true, protocol: nil}
    {:noreply, if(s.waiting_up, do: start_up(s), else: s)}
  end

  def handle_info(message, %{conn: conn} = s) when conn != nil do
    case Transport.handle_message(conn, message) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        {:noreply, if(s.held, do: s, else: received(s, bytes))}

      :closed ->
        {:noreply, %{s | conn: nil, held: true}}

      {:error, _} ->
        {:noreply, %{s | conn: nil, held: true}}

      :unknown ->
        {:noreply, s}
    end
  end

  def handle_info(_message, s), do: {:noreply, s}

  defp start_up(s) do
    protocol = Protocol.new(role: :active, rep_timeout: @never, start_timeout: @never)
    {protocol, frames, _events} = Protocol.connect(protocol)
    write(s, frames)
    %{s | protocol: protocol, held: false}
  end

  defp received(s, bytes) do
    {protocol, frames, events} = Protocol.handle_bytes(s.protocol, bytes)
    s = Enum.reduce(events, %{s | protocol: protocol}, &news/2)
    # held: the link went down on the peer's side, whose STRT would start it again at once
    unless s.held, do: write(s, frames)
    s
  end

  defp news(:up, s) do
    if s.waiting_up, do: GenServer.reply(s.waiting_up, :ok)
    %{s | waiting_up: nil}
  end

  defp news({:data, bytes}, s) do
    send(s.test, {:val_peer, self(), {:sent, bytes}})
    s
  end

  defp news(:peer_restarted, s) do
    send(s.test, {:val_peer, self(), :restart})
    %{s | held: true}
  end

  defp news({:down, _reason}, s), do: %{s | held: true}
  defp news(_other, s), do: s

  # A message in the running session (when there is one), as frames.
  defp data_frames(%{held: false} = s, bytes) do
    {:ok, _protocol, frames, _events} = Protocol.send(s.protocol, bytes, hold: false)
    frames
  end

  defp data_frames(_s, bytes), do: [Frame.data(1, 0, bytes)]

  defp write(%{conn: nil}, _frames), do: :ok
  defp write(_s, []), do: :ok
  defp write(s, frames), do: Transport.send(s.conn, Enum.map(frames, &Frame.encode/1))
end
