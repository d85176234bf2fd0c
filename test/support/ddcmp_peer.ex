defmodule Vws.Test.DDCMPPeer do
  @moduledoc """
  Plays the far end of a `Vws.Links.DDCMP` link with raw frames, for table tests.

  It listens on a fresh loopback endpoint (`endpoint/1`), accepts the link's connection (and the
  next one after `drop_connection/1`), and reports to the test process, in order:

    * `{:peer_raw, peer, bytes}` — each chunk of bytes received, undecoded;
    * `{:peer_frame, peer, frame}` — each frame decoded from them (`Vws.Links.DDCMP.Frame`);
    * `{:peer_bad, peer, %Vws.Links.DDCMP.Error{}}` — each decoding error;
    * `{:peer_connected, peer}` / `{:peer_closed, peer}`.

  `send_frames/2` and `send_raw/2` write to the link.
  """

  use GenServer

  alias Vws.Links.DDCMP.Frame
  alias Vws.Links.Transport

  def start_link(opts \\ []) do
    GenServer.start_link(__MODULE__, {self(), opts})
  end

  @doc "The loopback endpoint string the link should dial."
  def endpoint(peer), do: GenServer.call(peer, :endpoint)

  @doc "Sends frames (one DEL after each) as one chunk."
  def send_frames(peer, frames) when is_list(frames),
    do: GenServer.call(peer, {:send, Enum.map(frames, &Frame.encode/1)})

  def send_frames(peer, frame), do: send_frames(peer, [frame])

  @doc "Sends raw bytes as one chunk."
  def send_raw(peer, bytes), do: GenServer.call(peer, {:send, bytes})

  @doc "Closes the current connection; the next one the link dials is accepted."
  def drop_connection(peer), do: GenServer.call(peer, :drop)

  @impl true
  def init({test, opts}) do
    name = "ddcmp-peer-#{System.unique_integer([:positive])}"
    {:ok, listener} = Transport.listen("loopback:" <> name)

    state = %{
      test: test,
      listener: listener,
      endpoint: "loopback:" <> name,
      conn: nil,
      decoder: nil
    }

    {:ok, Map.put(state, :max_data, Keyword.get(opts, :max_data, 4096)), {:continue, :accept}}
  end

  @impl true
  def handle_continue(:accept, state) do
    # Accept in small slices so calls (endpoint/1 above all) are served while nobody dials.
    case Transport.accept(state.listener, 20) do
      {:ok, conn} ->
        :ok = Transport.activate(conn)
        send(state.test, {:peer_connected, self()})
        {:noreply, %{state | conn: conn, decoder: Frame.new(max_data: state.max_data)}}

      {:error, %Vws.Links.Transport.Error{reason: :timeout}} ->
        send(self(), :accept)
        {:noreply, state}
    end
  end

  @impl true
  def handle_call(:endpoint, _from, state), do: {:reply, state.endpoint, state}

  def handle_call({:send, iodata}, _from, %{conn: conn} = state) when conn != nil do
    {:reply, Transport.send(conn, iodata), state}
  end

  def handle_call(:drop, _from, %{conn: conn} = state) when conn != nil do
    Transport.close(conn)
    {:reply, :ok, %{state | conn: nil}, {:continue, :accept}}
  end

  @impl true
  def handle_info(:accept, %{conn: nil} = state), do: handle_continue(:accept, state)

  def handle_info(msg, %{conn: conn} = state) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        send(state.test, {:peer_raw, self(), bytes})
        {items, decoder} = Frame.feed(state.decoder, bytes)

        for item <- items do
          case item do
            {:error, error} -> send(state.test, {:peer_bad, self(), error})
            frame -> send(state.test, {:peer_frame, self(), frame})
          end
        end

        {:noreply, %{state | decoder: decoder}}

      :closed ->
        send(state.test, {:peer_closed, self()})
        {:noreply, %{state | conn: nil}, {:continue, :accept}}

      _other ->
        {:noreply, state}
    end
  end

  def handle_info(_msg, state), do: {:noreply, state}
end
