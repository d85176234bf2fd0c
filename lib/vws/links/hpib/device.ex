defmodule Vws.Links.HPIB.Device do
  @moduledoc false
  # One device on the HPIB: a gen_statem behind the `Vws.Links.HPIB` facade.
  #
  #   connecting ──ok──▶ ready ◀──answered, queue empty── busy ◀─┐ answered, next in queue
  #       ▲  └─failed─▶ disconnected ◀──timeout / closed──────┘ ──┘
  #       └──backoff───────┘
  #
  # The back-off (`Vws.Links.Backoff`) doubles with every wait in `disconnected` and is reset only by a
  # line from the device: a connection that is dropped before the device said anything counts
  # as a failed attempt. After a request's timeout the device is dialled again at once.
  #
  # `connecting` opens the endpoint (requests are postponed until it knows); `disconnected`
  # answers requests :not_connected at once and retries after the back-off; `ready` sends a
  # request and goes `busy` until every query of it is answered or its deadline passes. Requests
  # that arrive while busy wait in `queue` (visible in `info`), in arrival order.
  #
  # A repeatable request (`Vws.Codecs.SCPI.repeatable?/1`, every command of it) whose answer is damaged
  # or missing is tried again, at most `retries` times within its own deadline, each
  # try waiting its share of the request's time: the connection is closed and opened again
  # first (`connecting`, the request at the head of the queue), so that no late or shifted
  # answer line of the lost try can be taken for an answer to the next.
  @behaviour :gen_statem

  require Logger

  alias Vws.Codecs.SCPI
  alias Vws.Links.Connection
  alias Vws.Links.HPIB.Error

  @default_timeout 1_000
  @connect_timeout 1_000
  @backoff {50, 2_000}
  @retries 2

  @impl true
  def callback_mode, do: [:state_functions, :state_enter]

  @impl true
  def init(opts) do
    # The bus carries VWS_STATUS's polls, which run at high priority so that the node's other
    # work does not delay them (Vws.Partitions.VwsStatus): the bus does too. It only moves lines.
    Process.flag(:priority, :high)
    bus = Keyword.fetch!(opts, :bus)
    address = Keyword.fetch!(opts, :address)
    endpoint = Vws.Links.Endpoint.parse!(Keyword.fetch!(opts, :endpoint))
    Logger.metadata(hpib_bus: bus, hpib_address: address)
    metadata = %{bus: bus, address: address, endpoint: Vws.Links.Endpoint.to_string(endpoint)}

    data = %{
      bus: bus,
      address: address,
      device: Keyword.get(opts, :device),
      timeout: Keyword.get(opts, :timeout, @default_timeout),
      retries: Keyword.get(opts, :retries, @retries),
      retried: 0,
      # the connection, its back-off and the connect_failed event (Vws.Links.Connection); the
      # logs and the other events are this driver's own (Vws.LogLimit keeps them short)
      wire:
        Connection.new(
          endpoint: endpoint,
          backoff: Keyword.get(opts, :backoff, @backoff),
          connect: [timeout: Keyword.get(opts, :connect_timeout, @connect_timeout)],
          telemetry: {[:vws, :hpib], metadata}
        ),
      # how long :disconnected waits before dialling again (the shell's back-off)
      retry_in: 0,
      decoder: SCPI.new(),
      # the last request sent and its bytes (encoded/2)
      encoded: nil,
      current: nil,
      queue: :queue.new(),
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
    case Connection.connect(data.wire) do
      {:ok, wire} ->
        # reconnecting during trouble already told (a device that times out or drops every
        # connection) is part of that trouble, not news
        unless Vws.LogLimit.on?(:timeout) or Vws.LogLimit.on?(:lost),
          do: Logger.info("HPIB device #{data.address} connected to #{endpoint(data)}")

        telemetry(:connected, data, %{})

        # a request being tried again waits at the head of the queue
        serve(
          %{
            data
            | wire: wire,
              decoder: SCPI.new(),
              was_connected: true,
              connects: data.connects + 1,
              last_error: nil
          },
          []
        )

      {:error, reason, retry_in, wire} ->
        if data.was_connected do
          Logger.warning(
            "HPIB device #{data.address}: cannot connect to #{endpoint(data)}: #{inspect(reason)}"
          )
        end

        # the next attempt comes after the back-off's next wait (see disconnected/3)
        data = %{
          data
          | wire: wire,
            retry_in: retry_in,
            was_connected: false,
            last_error: {:connect, reason}
        }

        error = not_connected(data)

        queued =
          for {from, _, _} <- :queue.to_list(data.queue), do: {:reply, from, {:error, error}}

        {:next_state, :disconnected, %{data | queue: :queue.new()}, queued}
    end
  end

  def connecting({:call, _from}, {:request, _, _, _}, _data),
    do: {:keep_state_and_data, :postpone}

  def connecting(event, content, data), do: common(:connecting, event, content, data)

  ## disconnected

  def disconnected(:enter, _old, data),
    do: {:keep_state_and_data, [{:state_timeout, data.retry_in, :retry}]}

  def disconnected(:state_timeout, :retry, data), do: {:next_state, :connecting, data}

  def disconnected({:call, from}, {:request, _, _, _}, data) do
    {:keep_state, count_request(data), [{:reply, from, {:error, not_connected(data)}}]}
  end

  def disconnected(event, content, data), do: common(:disconnected, event, content, data)

  ## ready

  def ready(:enter, _old, _data), do: :keep_state_and_data

  def ready({:call, from}, {:request, _, _, _} = request, data) do
    data = count_request(data)
    serve(%{data | queue: :queue.in({from, request, 0}, data.queue)}, [])
  end

  def ready(:info, msg, data), do: transport_message(msg, data)
  def ready(event, content, data), do: common(:ready, event, content, data)

  ## busy

  def busy(:enter, _old, _data), do: :keep_state_and_data

  def busy({:call, from}, {:request, _, _, _} = request, data) do
    data = count_request(data)
    {:keep_state, %{data | queue: :queue.in({from, request, 0}, data.queue)}}
  end

  def busy(:state_timeout, :answer, data) do
    %{from: from, commands: commands, timeout: timeout} = data.current
    error = %Error{reason: :timeout, address: data.address, detail: timeout}
    telemetry(:timeout, data, %{commands: commands})
    data = %{data | timeouts: data.timeouts + 1}

    try_again(data, error, fn data ->
      Vws.LogLimit.warning(
        :timeout,
        "HPIB device #{data.address}: #{Exception.message(error)}; reconnecting"
      )

      # reconnect at once (the device may only have been slow); the requests queued behind this
      # one wait for the new connection
      telemetry(:disconnected, data, %{reason: :timeout})

      data = %{
        data
        | current: nil,
          wire: Connection.close(data.wire),
          decoder: SCPI.new(),
          last_error: :timeout
      }

      {:next_state, :connecting, data, [{:reply, from, {:error, error}}]}
    end)
  end

  def busy(:info, msg, data), do: transport_message(msg, data)
  def busy(event, content, data), do: common(:busy, event, content, data)

  ## Serving the queue

  # Sends the next request of the queue, skipping (and failing) those whose time ran out while
  # they waited; ends in `busy` with its deadline as the state timeout, or `ready`.
  defp serve(data, actions) do
    case :queue.out(data.queue) do
      {:empty, _} ->
        {:next_state, :ready, data, actions}

      {{:value, {from, {:request, commands, deadline, timeout}, tries}}, rest} ->
        data = %{data | queue: rest}
        timeout = timeout || data.timeout
        deadline = deadline || now() + timeout

        if deadline <= now() do
          # it waited its whole time behind other requests: never sent
          error = %Error{reason: :timeout, address: data.address, detail: timeout}
          serve(data, actions ++ [{:reply, from, {:error, error}}])
        else
          send_request(data, actions, from, commands, {deadline, timeout, tries})
        end
    end
  end

  defp send_request(data, actions, from, commands, {deadline, timeout, tries}) do
    {%{bytes: bytes, queries: queries, repeatable?: repeatable?}, data} = encoded(data, commands)

    case Connection.send(data.wire, bytes) do
      :ok ->
        case queries do
          [] ->
            serve(data, actions ++ [{:reply, from, {:ok, results(commands, [])}}])

          queries ->
            current = %{
              from: from,
              commands: commands,
              waiting: queries,
              answers: [],
              error: nil,
              timeout: timeout,
              deadline: deadline,
              tries: tries
            }

            # a try that may be followed by another waits its share of the time left
            tries_left = if repeatable?, do: max(data.retries - tries, 0), else: 0
            wait = div(max(deadline - now(), 0), tries_left + 1)

            {:next_state, :busy, %{data | current: current},
             actions ++ [{:state_timeout, wait, :answer}]}
        end

      {:error, reason} ->
        error = %Error{reason: :send_failed, address: data.address, detail: reason}
        lose_connection(data, {:send, reason}, actions ++ [{:reply, from, {:error, error}}])
    end
  end

  # The last request's bytes, its queries and whether it may be tried again are kept:
  # VWS_STATUS sends the same poll every 20 ms.
  defp encoded(%{encoded: {commands, request}} = data, commands), do: {request, data}

  defp encoded(data, commands) do
    request = %{
      bytes: commands |> Enum.map(&SCPI.encode_command/1) |> IO.iodata_to_binary(),
      queries: Enum.filter(commands, &SCPI.response?/1),
      repeatable?: repeatable?(commands)
    }

    {request, %{data | encoded: {commands, request}}}
  end

  ## Bytes from the device

  defp transport_message(msg, data) do
    case Connection.handle_message(data.wire, msg) do
      {:data, bytes} ->
        {lines, decoder} = SCPI.feed(data.decoder, bytes)
        # the device answers: this connection works, a later loss is dialled again soon
        data = if lines == [], do: data, else: %{data | wire: Connection.alive(data.wire)}
        lines |> Enum.reduce(%{data | decoder: decoder}, &line/2) |> answered()

      {:closed, {:transport, reason}} ->
        connection_closed(data, reason)

      {:closed, reason} ->
        connection_closed(data, reason)

      :unknown ->
        Logger.debug("HPIB device: unexpected message #{inspect(msg, limit: 10)}")
        :keep_state_and_data
    end
  end

  # One answer line: the answer to the oldest query still waiting, or unsolicited.
  defp line(line, %{current: %{waiting: [query | rest]} = c} = data) do
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

    %{data | current: %{c | waiting: rest, answers: [answer | c.answers], error: error}}
  end

  defp line(line, data) do
    Vws.LogLimit.warning(:unsolicited, fn ->
      "HPIB device #{data.address}: unsolicited line #{inspect(line, limit: 10)}"
    end)

    %{data | unsolicited: data.unsolicited + 1}
  end

  defp answered(%{current: %{waiting: [], error: nil} = c} = data) do
    reply = {:ok, results(c.commands, Enum.reverse(c.answers))}
    # a good answer ends the troubles logged once each (Vws.LogLimit)
    # (the texts built only when one was on: this runs at every answer)
    Vws.LogLimit.clear(:timeout, fn -> "HPIB device #{data.address} answers again" end)

    Vws.LogLimit.clear(:lost, fn ->
      "HPIB device #{data.address} keeps its connection again"
    end)

    Vws.LogLimit.clear(:unsolicited, fn -> "HPIB device #{data.address}: unsolicited lines" end)
    serve(%{data | current: nil}, [{:reply, c.from, reply}])
  end

  defp answered(%{current: %{waiting: []} = c} = data) do
    error = %Error{reason: :bad_response, address: data.address, detail: c.error}

    try_again(data, error, fn data ->
      serve(%{data | current: nil}, [{:reply, c.from, {:error, error}}])
    end)
  end

  defp answered(data), do: {:keep_state, data}

  defp connection_closed(data, reason) do
    Vws.LogLimit.warning(
      :lost,
      "HPIB device #{data.address}: connection lost (#{inspect(reason)})"
    )

    actions =
      case data.current do
        %{from: from} ->
          [
            {:reply, from,
             {:error, %Error{reason: :closed, address: data.address, detail: reason}}}
          ]

        nil ->
          []
      end

    # a peer that closes is not a damaged line: no try again, the back-off decides when to dial
    lose_connection(%{data | current: nil}, reason, actions)
  end

  # The request in progress failed with `error`: tried again on a new connection if it is
  # repeatable and has tries and time left, else `give_up.(data)`.
  defp try_again(%{current: c} = data, error, give_up) do
    if c.tries < data.retries and repeatable?(c.commands) and now() < c.deadline do
      telemetry(:retry, data, %{commands: c.commands, reason: error.reason, try: c.tries + 1})
      request = {c.from, {:request, c.commands, c.deadline, c.timeout}, c.tries + 1}

      {:next_state, :connecting,
       %{
         data
         | current: nil,
           wire: Connection.close(data.wire),
           decoder: SCPI.new(),
           retried: data.retried + 1,
           queue: :queue.in_r(request, data.queue)
       }}
    else
      give_up.(data)
    end
  end

  defp repeatable?(commands), do: Enum.all?(commands, &SCPI.repeatable?/1)

  # Closes the connection; every request still queued fails :not_connected.
  defp lose_connection(data, reason, actions) do
    {retry_in, wire} = Connection.lost(data.wire, reason)
    telemetry(:disconnected, data, %{reason: reason})
    data = %{data | wire: wire, retry_in: retry_in, decoder: SCPI.new(), last_error: reason}
    error = not_connected(data)

    queued =
      for {from, _request, _tries} <- :queue.to_list(data.queue),
          do: {:reply, from, {:error, error}}

    {:next_state, :disconnected, %{data | queue: :queue.new()}, actions ++ queued}
  end

  ## Every state

  defp common(state, {:call, from}, :info, data) do
    info = %{
      state: state,
      device: data.device,
      address: data.address,
      endpoint: endpoint(data),
      connects: data.connects,
      timeouts: data.timeouts,
      retried: data.retried,
      requests: data.requests,
      queued: :queue.len(data.queue),
      unsolicited: data.unsolicited,
      last_error: data.last_error
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  # Vws.Links.HPIB's requests come with the caller's deadline (Vws.Links.Connection); a request
  # without a timeout of its own has the device's, from now
  # (a request straight to its event, not through the {:deadline, …} one: every poll is one)
  defp common(_state, :cast, {Connection, from, deadline, {:request, commands, timeout}}, data),
    do:
      {:keep_state_and_data,
       [{:next_event, {:call, from}, request(commands, deadline, timeout, data)}]}

  defp common(_state, :cast, {Connection, _, _, _} = call, _data),
    do: {:keep_state_and_data, [Connection.as_call(call)]}

  defp common(_state, {:call, from}, {:deadline, deadline, {:request, commands, timeout}}, data),
    do:
      {:keep_state_and_data,
       [{:next_event, {:call, from}, request(commands, deadline, timeout, data)}]}

  defp common(_state, {:call, from}, {:deadline, _deadline, :await_connected}, _data),
    do: {:keep_state_and_data, [{:next_event, {:call, from}, :await_connected}]}

  # Vws.Links.HPIB.await_connected/2: answered once connected, postponed until then
  defp common(state, {:call, from}, :await_connected, _data) do
    if state in [:ready, :busy],
      do: {:keep_state_and_data, [{:reply, from, :ok}]},
      else: {:keep_state_and_data, :postpone}
  end

  defp common(_state, :info, msg, _data) do
    Logger.debug("HPIB device: unexpected message #{inspect(msg, limit: 10)}")
    :keep_state_and_data
  end

  defp common(_state, event, content, _data) do
    Logger.warning("HPIB device: unexpected #{inspect(event)} #{inspect(content, limit: 10)}")
    :keep_state_and_data
  end

  defp request(commands, deadline, timeout, data) do
    deadline = if timeout, do: deadline, else: now() + data.timeout
    {:request, commands, deadline, timeout}
  end

  # Results in command order: the answers of the queries, :ok for the others.
  defp results(commands, answers) when length(commands) == length(answers), do: answers

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

  defp not_connected(data),
    do: %Error{reason: :not_connected, address: data.address, detail: data.last_error}

  defp count_request(data), do: %{data | requests: data.requests + 1}

  defp telemetry(what, data, extra, measurements \\ %{}) do
    Vws.Telemetry.execute(
      [:vws, :hpib, what],
      Map.put(measurements, :count, 1),
      Map.merge(%{bus: data.bus, address: data.address, endpoint: endpoint(data)}, extra)
    )
  end

  defp endpoint(data), do: Vws.Links.Endpoint.to_string(data.wire.endpoint)
  defp now, do: System.monotonic_time(:millisecond)
end
