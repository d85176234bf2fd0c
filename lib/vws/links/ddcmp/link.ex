defmodule Vws.Links.DDCMP.Link do
  @moduledoc false
  # The process behind `Vws.Links.DDCMP`: a transport and a `Vws.Links.DDCMP.Protocol`, nothing more. The
  # protocol (states, sequence numbers, what to send, which timer to arm) is the pure core; this
  # process dials (with back-off, `Vws.Links.Connection`), hands received bytes, requests and expired timers to the core,
  # writes the frames it returns, arms its timers and tells the owner its news
  # (`Vws.Links.DDCMP.Wire`). Its own state says only whether a transport is there.

  @behaviour :gen_statem

  require Logger

  alias Vws.Links.Connection
  alias Vws.Links.DDCMP.{Protocol, Wire}

  defstruct [:owner, :name, :workstation, :wire, :protocol]

  @impl :gen_statem
  def callback_mode, do: :handle_event_function

  @impl :gen_statem
  def init(opts) do
    if ws = Keyword.get(opts, :workstation), do: Logger.metadata(workstation: ws)
    endpoint = Keyword.get(opts, :endpoint)
    name = Keyword.get(opts, :name)
    workstation = Keyword.get(opts, :workstation)

    data = %__MODULE__{
      owner: Keyword.fetch!(opts, :owner),
      name: name,
      workstation: workstation,
      # the back-off doubles with every wait, back to the minimum when the link runs
      wire:
        Connection.new(
          endpoint: endpoint,
          backoff: Keyword.fetch!(opts, :backoff),
          telemetry: {[:vws, :ddcmp], %{link: name || self(), workstation: workstation}},
          label: "DDCMP link #{inspect(name || self())}"
        ),
      protocol:
        Protocol.new([halt_reason: if(endpoint, do: :disconnected, else: :attaching)] ++ opts)
    }

    # never dial in init/1: the first dial is an event
    actions = if endpoint, do: [{{:timeout, :connect}, 0, :connect}], else: []
    {:ok, :disconnected, data, actions}
  end

  @impl :gen_statem
  def terminate(_reason, _state, %__MODULE__{wire: wire}) do
    Connection.close(wire)
    :ok
  end

  @impl :gen_statem
  def handle_event({:timeout, :connect}, :connect, :disconnected, data) do
    case Connection.connect(data.wire) do
      {:ok, wire} ->
        connected(%__MODULE__{data | wire: wire})

      {:error, reason, retry_in, wire} ->
        protocol = %Protocol{data.protocol | last_error: {:connect, reason}}

        {:keep_state, %__MODULE__{data | wire: wire, protocol: protocol},
         [{{:timeout, :connect}, retry_in, :connect}]}
    end
  end

  def handle_event(
        {:call, from},
        {:attach, conn},
        :disconnected,
        %__MODULE__{wire: %Connection{endpoint: nil, conn: nil}} = data
      ) do
    connected(%__MODULE__{data | wire: Connection.attach(data.wire, conn)}, [{:reply, from, :ok}])
  end

  def handle_event(:cast, {Connection, _, _, _} = call, _state, _data),
    do: {:keep_state_and_data, [Connection.as_call(call)]}

  def handle_event({:call, from}, {:deadline, _deadline, request}, state, data),
    do: handle_event({:call, from}, request, state, data)

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
      |> Map.merge(%{connected: Connection.connected?(data.wire), peer: data.wire.peer})

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  def handle_event({:timeout, timer}, timer, _state, data) when timer in [:rep, :start] do
    run(data, Protocol.handle_timeout(data.protocol, timer))
  end

  def handle_event(:info, message, :connected, data) do
    case Connection.handle_message(data.wire, message) do
      {:data, bytes} -> run(data, Protocol.handle_bytes(data.protocol, bytes))
      {:closed, reason} -> disconnected(data, reason)
      :unknown -> unexpected(data, :info, message)
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
    was_running = Protocol.running?(data.protocol)
    {retry_in, wire} = Connection.lost(data.wire, reason)
    data = %__MODULE__{data | wire: wire}
    {:keep_state, data, actions} = run(data, Protocol.disconnected(data.protocol, reason))

    if wire.endpoint do
      {:next_state, :disconnected, data, actions ++ [{{:timeout, :connect}, retry_in, :connect}]}
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
    {news, timers} = Wire.perform(frames, events, data.wire.conn, meta(data))
    Enum.each(news, &notify(data, &1))
    wire = if :up in news, do: Connection.alive(data.wire), else: data.wire
    {:keep_state, %__MODULE__{data | protocol: protocol, wire: wire}, timers ++ actions}
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
