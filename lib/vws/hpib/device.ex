defmodule Vws.HPIB.Device do
  @moduledoc false
  # One device on the HPIB: a gen_statem behind the `Vws.HPIB` facade.
  #
  #   connecting ──ok──▶ ready ◀──answered── busy
  #       ▲  └─failed─▶ disconnected ◀──timeout/closed──┘
  #       └──backoff───────┘
  #
  # `connecting` opens the endpoint (requests wait, postponed); `disconnected` answers requests
  # :not_connected at once and retries after the back-off; `ready` sends a request and goes
  # `busy` until every query of it is answered (requests wait, postponed) or its deadline passes.
  @behaviour :gen_statem

  require Logger

  alias Vws.{SCPI, Transport}
  alias Vws.HPIB.Error

  @default_timeout 1_000
  @connect_timeout 1_000
  @backoff {50, 2_000}

  @impl true
  def callback_mode, do: [:state_functions, :state_enter]

  @impl true
  def init(opts) do
    bus = Keyword.fetch!(opts, :bus)
    address = Keyword.fetch!(opts, :address)
    endpoint = Vws.Endpoint.parse!(Keyword.fetch!(opts, :endpoint))
    {first, max} = Keyword.get(opts, :backoff, @backoff)
    Logger.metadata(hpib_bus: bus, hpib_address: address)

    data = %{
      bus: bus,
      address: address,
      endpoint: endpoint,
      timeout: Keyword.get(opts, :timeout, @default_timeout),
      connect_timeout: Keyword.get(opts, :connect_timeout, @connect_timeout),
      backoff_first: first,
      backoff_max: max,
      backoff: first,
      conn: nil,
      decoder: SCPI.new(),
      current: nil,
      was_connected: false,
      connects: 0,
      timeouts: 0,
      requests: 0,
      unsolicited: 0,
      last_error: nil
    }

    {:ok, :connecting, data}
  end

  ## connecting

  def connecting(:enter, _old, _data), do: {:keep_state_and_data, [{:state_timeout, 0, :connect}]}

  def connecting(:state_timeout, :connect, data) do
    case Transport.connect(data.endpoint, timeout: data.connect_timeout) do
      {:ok, conn} ->
        :ok = Transport.activate(conn)
        Logger.info("HPIB device #{data.address} connected to #{endpoint(data)}")
        telemetry(:connected, data, %{})

        {:next_state, :ready,
         %{
           data
           | conn: conn,
             decoder: SCPI.new(),
             backoff: data.backoff_first,
             was_connected: true,
             connects: data.connects + 1,
             last_error: nil
         }}

      {:error, reason} ->
        if data.was_connected,
          do:
            Logger.warning(
              "HPIB device #{data.address}: cannot connect to #{endpoint(data)}: #{inspect(reason)}"
            ),
          else: Logger.debug("HPIB device #{data.address}: cannot connect: #{inspect(reason)}")

        {:next_state, :disconnected,
         %{data | was_connected: false, last_error: {:connect, reason}}}
    end
  end

  def connecting({:call, _from}, {:request, _, _, _}, _data),
    do: {:keep_state_and_data, :postpone}

  def connecting(event, content, data), do: common(:connecting, event, content, data)

  ## disconnected

  def disconnected(:enter, _old, data) do
    backoff = data.backoff
    next = backoff |> Kernel.*(2) |> max(data.backoff_first) |> min(data.backoff_max)
    {:keep_state, %{data | backoff: next}, [{:state_timeout, backoff, :retry}]}
  end

  def disconnected(:state_timeout, :retry, data), do: {:next_state, :connecting, data}

  def disconnected({:call, from}, {:request, _commands, _deadline, _timeout}, data) do
    error = %Error{reason: :not_connected, address: data.address, detail: data.last_error}
    {:keep_state, count_request(data), [{:reply, from, {:error, error}}]}
  end

  def disconnected(event, content, data), do: common(:disconnected, event, content, data)

  ## ready

  def ready(:enter, _old, _data), do: :keep_state_and_data

  def ready({:call, from}, {:request, commands, deadline, timeout}, data) do
    data = count_request(data)
    timeout = timeout || data.timeout
    deadline = deadline || now() + timeout

    if deadline <= now() do
      # it waited its whole time behind other requests: never sent
      {:keep_state, data, [{:reply, from, {:error, timeout_error(data, timeout)}}]}
    else
      case Transport.send(data.conn, Enum.map(commands, &SCPI.encode_command/1)) do
        :ok ->
          queries = Enum.filter(commands, &SCPI.response?/1)

          current = %{
            from: from,
            commands: commands,
            waiting: queries,
            answers: [],
            error: nil,
            deadline: deadline,
            timeout: timeout
          }

          if queries == [] do
            {:keep_state, data, [{:reply, from, {:ok, results(commands, [])}}]}
          else
            {:next_state, :busy, %{data | current: current}}
          end

        {:error, reason} ->
          error = %Error{reason: :send_failed, address: data.address, detail: reason}
          data = drop_connection(data, {:send, reason})
          {:next_state, :disconnected, data, [{:reply, from, {:error, error}}]}
      end
    end
  end

  def ready(:info, msg, data), do: transport_message(msg, :ready, data)
  def ready(event, content, data), do: common(:ready, event, content, data)

  ## busy

  def busy(:enter, _old, data) do
    {:keep_state_and_data, [{:state_timeout, max(data.current.deadline - now(), 0), :answer}]}
  end

  def busy({:call, _from}, {:request, _, _, _}, _data), do: {:keep_state_and_data, :postpone}

  def busy(:state_timeout, :answer, data) do
    %{from: from, commands: commands, timeout: timeout} = data.current
    error = timeout_error(data, timeout)
    Logger.warning("HPIB device #{data.address}: #{Exception.message(error)}; reconnecting")
    telemetry(:timeout, data, %{commands: commands})
    data = drop_connection(%{data | current: nil, timeouts: data.timeouts + 1}, :timeout)
    # reconnect at once: the device may only have been slow
    data = %{data | backoff: 0}
    {:next_state, :disconnected, data, [{:reply, from, {:error, error}}]}
  end

  def busy(:info, msg, data), do: transport_message(msg, :busy, data)
  def busy(event, content, data), do: common(:busy, event, content, data)

  ## every state

  defp common(state, {:call, from}, :info, data) do
    info = %{
      state: state,
      address: data.address,
      endpoint: endpoint(data),
      connects: data.connects,
      timeouts: data.timeouts,
      requests: data.requests,
      unsolicited: data.unsolicited,
      last_error: data.last_error
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  defp common(_state, :info, msg, _data) do
    Logger.debug("HPIB device: unexpected message #{inspect(msg, limit: 10)}")
    :keep_state_and_data
  end

  defp common(_state, event, content, _data) do
    Logger.warning("HPIB device: unexpected #{inspect(event)} #{inspect(content, limit: 10)}")
    :keep_state_and_data
  end

  defp transport_message(msg, state, data) do
    case Transport.handle_message(data.conn, msg) do
      {:data, bytes} ->
        Transport.activate(data.conn)
        {lines, decoder} = SCPI.feed(data.decoder, bytes)
        Enum.reduce(lines, {state, %{data | decoder: decoder}}, &line/2) |> settle(state)

      :closed ->
        lost(data, :closed)

      {:error, reason} ->
        lost(data, reason)

      :unknown ->
        common(state, :info, msg, data)
    end
  end

  # One answer line: the answer to the oldest query still waiting, or unsolicited.
  defp line(line, {state, %{current: %{waiting: [query | rest]} = c} = data}) do
    {answer, error} =
      case line do
        {:error, e} ->
          {nil, c.error || e}

        text ->
          case SCPI.decode_response(query, text) do
            {:ok, response} -> {response, c.error}
            {:error, e} -> {nil, c.error || e}
          end
      end

    {state, %{data | current: %{c | waiting: rest, answers: [answer | c.answers], error: error}}}
  end

  defp line(line, {state, data}) do
    Logger.warning("HPIB device #{data.address}: unsolicited line #{inspect(line, limit: 10)}")
    {state, %{data | unsolicited: data.unsolicited + 1}}
  end

  defp settle({_state, %{current: %{waiting: []} = c} = data}, _old) do
    reply =
      if c.error,
        do: {:error, %Error{reason: :bad_response, address: data.address, detail: c.error}},
        else: {:ok, results(c.commands, Enum.reverse(c.answers))}

    {:next_state, :ready, %{data | current: nil}, [{:reply, c.from, reply}]}
  end

  defp settle({_state, data}, _old), do: {:keep_state, data}

  defp lost(data, reason) do
    Logger.warning("HPIB device #{data.address}: connection lost (#{inspect(reason)})")

    actions =
      case data.current do
        %{from: from} ->
          [{:reply, from, {:error, %Error{reason: :closed, address: data.address}}}]

        nil ->
          []
      end

    data = drop_connection(%{data | current: nil}, reason)
    {:next_state, :disconnected, data, actions}
  end

  defp drop_connection(data, reason) do
    if data.conn, do: Transport.close(data.conn)
    telemetry(:disconnected, data, %{reason: reason})
    %{data | conn: nil, decoder: SCPI.new(), last_error: reason}
  end

  # Results in command order: the answers of the queries, :ok for the others.
  defp results(commands, answers) do
    {results, []} =
      Enum.map_reduce(commands, answers, fn command, answers ->
        if SCPI.response?(command) do
          [answer | rest] = answers
          {answer, rest}
        else
          {:ok, answers}
        end
      end)

    results
  end

  defp timeout_error(data, timeout),
    do: %Error{reason: :timeout, address: data.address, detail: timeout}

  defp count_request(data), do: %{data | requests: data.requests + 1}

  defp telemetry(what, data, extra) do
    Vws.Telemetry.execute(
      [:vws, :hpib, what],
      %{count: 1},
      Map.merge(%{bus: data.bus, address: data.address, endpoint: endpoint(data)}, extra)
    )
  end

  defp endpoint(data), do: Vws.Endpoint.to_string(data.endpoint)
  defp now, do: System.monotonic_time(:millisecond)
end
