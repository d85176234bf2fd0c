defmodule Vws.Links.DDCMP.Link do
  @moduledoc false
  # The process behind `Vws.Links.DDCMP`: a transport and a `Vws.Links.DDCMP.Protocol`, nothing more. The
  # protocol (states, sequence numbers, what to send, which timer to arm) is the pure core; this
  # process dials (with back-off), hands received bytes, requests and expired timers to the core,
  # writes the frames it returns, arms its timers and tells the owner its news
  # (`Vws.Links.DDCMP.Wire`). Its own state says only whether a transport is there.

  @behaviour :gen_statem

  require Logger

  alias Vws.Links.DDCMP.{Protocol, Wire}
  alias Vws.Links.Transport

  defstruct [:owner, :name, :workstation, :endpoint, :backoff, :conn, :protocol, dialled: false]

  @impl :gen_statem
  def callback_mode, do: :handle_event_function

  @impl :gen_statem
  def init(opts) do
    {min_backoff, max_backoff} = Keyword.fetch!(opts, :backoff)
    if ws = Keyword.get(opts, :workstation), do: Logger.metadata(workstation: ws)
    endpoint = Keyword.get(opts, :endpoint)

    data = %__MODULE__{
      owner: Keyword.fetch!(opts, :owner),
      name: Keyword.get(opts, :name),
      workstation: Keyword.get(opts, :workstation),
      endpoint: endpoint,
      # doubles with every wait, back to the minimum when the link runs (Vws.Links.Backoff)
      backoff: Vws.Links.Backoff.new(min_backoff, max_backoff),
      protocol:
        Protocol.new([halt_reason: if(endpoint, do: :disconnected, else: :attaching)] ++ opts)
    }

    # never dial in init/1: the first dial is an event
    actions = if endpoint, do: [{{:timeout, :connect}, 0, :connect}], else: []
    {:ok, :disconnected, data, actions}
  end

  @impl :gen_statem
  def terminate(_reason, _state, %__MODULE__{conn: conn}) do
    if conn, do: Transport.close(conn)
    :ok
  end

  @impl :gen_statem
  def handle_event({:timeout, :connect}, :connect, :disconnected, data) do
    data = %__MODULE__{data | dialled: true}

    case Transport.connect(data.endpoint) do
      {:ok, conn} ->
        :ok = Transport.activate(conn)
        connected(%__MODULE__{data | conn: conn})

      {:error, reason} ->
        {delay, backoff} = Vws.Links.Backoff.next(data.backoff)

        Wire.telemetry(meta(data), :connect_failed, %{count: 1, retry_in: delay}, %{
          endpoint: to_string(data.endpoint),
          reason: reason
        })

        protocol = %Protocol{data.protocol | last_error: {:connect, reason}}

        {:keep_state, %__MODULE__{data | backoff: backoff, protocol: protocol},
         [{{:timeout, :connect}, delay, :connect}]}
    end
  end

  def handle_event(
        {:call, from},
        {:attach, conn},
        :disconnected,
        %__MODULE__{endpoint: nil} = data
      )
      when data.conn == nil do
    :ok = Transport.activate(conn)
    connected(%__MODULE__{data | conn: conn}, [{:reply, from, :ok}])
  end

  def handle_event({:call, from}, {:send, bytes, opts}, _state, data) when is_binary(bytes) do
    case Protocol.send(data.protocol, bytes, opts) do
      {:ok, protocol, frames, events} ->
        run(data, {protocol, frames, events}, [{:reply, from, :ok}])

      {:error, reason} ->
        {:keep_state_and_data, [{:reply, from, {:error, reason}}]}
    end
  end

  def handle_event({:call, from}, :restart, _state, data) do
    run(data, Protocol.restart(data.protocol), [{:reply, from, :ok}])
  end

  def handle_event({:call, from}, :info, _state, data) do
    info =
      data.protocol
      |> Protocol.info()
      |> Map.merge(%{connected: data.conn != nil, peer: data.conn && Transport.peer(data.conn)})

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  def handle_event({:timeout, timer}, timer, _state, data) when timer in [:rep, :start] do
    run(data, Protocol.handle_timeout(data.protocol, timer))
  end

  def handle_event(:info, message, :connected, %__MODULE__{conn: conn} = data) do
    case Transport.handle_message(conn, message) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        run(data, Protocol.handle_bytes(data.protocol, bytes))

      :closed ->
        disconnected(data, :closed)

      {:error, reason} ->
        disconnected(data, {:transport, reason})

      :unknown ->
        unexpected(data, :info, message)
    end
  end

  def handle_event({:call, from}, content, _state, data) do
    {:keep_state, data, actions} = unexpected(data, :call, content)
    {:keep_state, data, [{:reply, from, {:error, :unknown_call}} | actions]}
  end

  def handle_event(type, content, _state, data), do: unexpected(data, type, content)

  defp connected(data, actions \\ []) do
    {:keep_state, data, more} = run(data, Protocol.connect(data.protocol), actions)
    {:next_state, :connected, data, more}
  end

  defp disconnected(data, reason) do
    Transport.close(data.conn)
    was_running = Protocol.running?(data.protocol)
    data = %__MODULE__{data | conn: nil}
    {:keep_state, data, actions} = run(data, Protocol.disconnected(data.protocol, reason))

    if data.endpoint do
      {delay, backoff} = Vws.Links.Backoff.next(data.backoff)

      {:next_state, :disconnected, %__MODULE__{data | backoff: backoff},
       actions ++ [{{:timeout, :connect}, delay, :connect}]}
    else
      # A handed-over connection cannot be dialled again: the link's life ends with it, and the
      # owner always hears of it.
      unless was_running do
        Wire.telemetry(meta(data), :link_down, %{count: 1}, %{reason: reason})
        notify(data, {:down, reason})
      end

      {:stop, :normal, data}
    end
  end

  defp run(data, {protocol, frames, events}, actions \\ []) do
    {news, timers} = Wire.perform(frames, events, data.conn, meta(data))
    Enum.each(news, &notify(data, &1))

    backoff = if :up in news, do: Vws.Links.Backoff.reset(data.backoff), else: data.backoff

    {:keep_state, %__MODULE__{data | protocol: protocol, backoff: backoff}, timers ++ actions}
  end

  defp unexpected(data, type, content) do
    Logger.warning(
      "DDCMP link #{inspect(data.name || self())} in #{Protocol.state(data.protocol)}: " <>
        "unexpected #{inspect(type)} " <> inspect(content, limit: 10)
    )

    {:keep_state, %__MODULE__{data | protocol: Protocol.count_unexpected(data.protocol)}, []}
  end

  defp meta(data), do: %{link: data.name || self(), workstation: data.workstation}

  defp notify(data, event) do
    case resolve(data.owner) do
      nil -> :ok
      pid -> send(pid, {:ddcmp, self(), event})
    end
  end

  defp resolve(pid) when is_pid(pid), do: pid
  defp resolve(name), do: GenServer.whereis(name)
end
