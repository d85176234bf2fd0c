defmodule Vws.Links.VAL.Connection do
  @moduledoc false
  # The gen_statem behind `Vws.Links.VAL`: one process for the whole wire — the transport, the DDCMP
  # protocol (`Vws.Links.DDCMP.Protocol`, pure data driven from here) and the VAL II logical units
  # above it. Bytes from the transport go to the protocol; its news (`:up`, `{:data, _}`,
  # `{:down, _}`, `:peer_restarted`) is handled here in the order the protocol produced it, in the
  # same callback, so the units always know the link's state as it is: no session to count, no
  # mailbox to peek into.
  #
  # Its state is a pair {lun2, activity}:
  #
  #   lun2      :down   the DDCMP link is not running
  #             :idle   link up, no prompt outstanding (waiting for LUN 2 READ)
  #             :ready  a prompt is outstanding: one command may be sent
  #             :busy   a command was sent; its numbered response is awaited
  #   activity  :still  nothing in flight on the arm
  #             :moving a DO (or EXECUTE) was accepted and its MOTION (PROGRAM) COMPLETE is awaited
  #
  # The two halves change independently (LUN 2 and LUN 3 are independent logical units), hence
  # handle_event_function over a pair rather than one state function per combination.
  #
  # Requests are queued by hand rather than postponed: each has a deadline, and a robot move
  # whose caller has given up must never be sent late, so a queued request needs its own timer
  # and can be withdrawn; a postponed event cannot.
  #
  # What the units send in one callback is collected in `out` and given to the protocol when the
  # callback ends, after every piece of news it brought; a queued command goes (`dispatch/3`)
  # only then, on the state the whole chunk left. Replies collected before the link went down or
  # restarted within the same chunk are dropped: they answer a session that has ended.
  @behaviour :gen_statem

  require Logger

  alias Vws.Links.Connection
  alias Vws.Links.DDCMP.{Protocol, Wire}
  alias Vws.Links.VAL.Message

  @lun_short_status 1
  @lun_monitor 2
  @lun_async 3
  @max_async 10

  @impl true
  def callback_mode, do: :handle_event_function

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    name = Keyword.get(opts, :name, self())
    ddcmp = Keyword.fetch!(opts, :ddcmp)
    workstation = Keyword.get(ddcmp, :workstation) || Vws.Names.id_of(name)
    Logger.metadata(val: inspect(name), workstation: workstation)
    line_meta = %{link: name, workstation: workstation}

    data = %{
      name: name,
      # the transport and its back-off, back to the minimum once the link runs
      wire:
        Connection.new(
          endpoint: Keyword.fetch!(ddcmp, :endpoint),
          backoff: Keyword.fetch!(ddcmp, :backoff),
          telemetry: {[:vws, :ddcmp], line_meta},
          label: "VAL II link"
        ),
      protocol: Protocol.new(Keyword.put(ddcmp, :role, :active)),
      line_meta: line_meta,
      # VAL messages to give to the protocol when the callback ends
      out: [],
      queue: [],
      lun2_request: nil,
      activity_request: nil,
      requests: %{},
      prompt: nil,
      # why the link's transport is gone (the peer closed it, or it failed), until it is up again
      gone: nil,
      short_status: nil,
      last_async: [],
      counts: %{in: 0, out: 0, bad: 0, stale: 0, unexpected: 0, requests: 0, errors: 0}
    }

    # never dial in init: the first dial is an event
    {:ok, {:down, :still}, data, [{{:timeout, :connect}, 0, :connect}]}
  end

  @impl true
  def handle_event({:timeout, :connect}, :connect, state, data) do
    case Connection.connect(data.wire) do
      {:ok, wire} ->
        line(state, %{data | wire: wire}, Protocol.connect(data.protocol))

      {:error, reason, retry_in, wire} ->
        protocol = %Protocol{data.protocol | last_error: {:connect, reason}}

        {:keep_state, %{data | wire: wire, protocol: protocol},
         [{{:timeout, :connect}, retry_in, :connect}]}
    end
  end

  def handle_event({:timeout, timer}, timer, state, data) when timer in [:rep, :start] do
    line(state, data, Protocol.handle_timeout(data.protocol, timer))
  end

  # Requests -----------------------------------------------------------------------------------

  # Vws.Links.VAL.request/3: the caller's deadline comes with it (Vws.Links.Connection)
  def handle_event(:cast, {Connection, _, _, _} = call, _state, _data),
    do: {:keep_state_and_data, [Connection.as_call(call)]}

  def handle_event({:call, from}, {:deadline, deadline, {:request, text, wait}}, state, data),
    do: handle_event({:call, from}, {:request, text, wait, deadline}, state, data)

  # The controller cannot be reached (the transport is gone and is being dialled again): the
  # request fails now rather than wait to be sent whenever the robot is back.
  def handle_event({:call, from}, {:request, _, _, _}, _state, %{gone: reason} = data)
      when reason != nil do
    {:keep_state, count(data, :errors), [{:reply, from, {:error, {:link_down, reason}}}]}
  end

  def handle_event({:call, from}, {:request, text, wait, deadline}, state, data) do
    case Message.new(@lun_monitor, :write, 0, text) do
      {:ok, _} ->
        ref = make_ref()

        request = %{
          ref: ref,
          from: from,
          text: text,
          wait: wait,
          response: nil,
          complete: false,
          started: System.monotonic_time(),
          deadline: deadline
        }

        data = %{
          data
          | requests: Map.put(data.requests, ref, request),
            queue: data.queue ++ [ref]
        }

        timer =
          if deadline == :infinity,
            do: [],
            else: [{{:timeout, {:request, ref}}, max(deadline - now(), 0), nil}]

        done(state, data, timer)

      {:error, error} ->
        {:keep_state_and_data, [{:reply, from, {:error, {:bad_command, error}}}]}
    end
  end

  def handle_event({:call, from}, :info, state, data) do
    info = %{
      state: state,
      line:
        data.protocol
        |> Protocol.info()
        |> Map.merge(%{connected: Connection.connected?(data.wire), peer: data.wire.peer}),
      prompt: data.prompt,
      short_status: data.short_status,
      last_async: Enum.reverse(data.last_async),
      queued: length(data.queue),
      in_flight:
        for(
          ref <- Enum.uniq(Enum.reject([data.lun2_request, data.activity_request], &is_nil/1)),
          do: data.requests[ref].text
        ),
      counts: data.counts
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  def handle_event({:call, from}, :reinitialise, {lun2, activity}, data) do
    if lun2 == :busy or activity == :moving do
      {:keep_state_and_data, [{:reply, from, {:error, :busy}}]}
    else
      # the link goes back through start-up ({:down, :restart} if it was running); the units wait
      # for it and a fresh prompt
      line({:down, :still}, %{data | prompt: nil}, Protocol.restart(data.protocol), [
        {:reply, from, :ok}
      ])
    end
  end

  def handle_event({:timeout, {:request, ref}}, nil, state, data) do
    case data.requests[ref] do
      nil ->
        :keep_state_and_data

      request ->
        if ref in data.queue do
          # never sent: withdraw it
          data = %{data | queue: List.delete(data.queue, ref)}
          {data, actions} = finish(data, request, {:error, :timeout})
          {:next_state, state, data, actions}
        else
          # sent: the caller is told, the protocol state stays until the controller answers
          Logger.warning("#{inspect(request.text)} timed out waiting for the VAL II")
          reply = if request.from, do: [{:reply, request.from, {:error, :timeout}}], else: []
          data = put_in(data.requests[ref].from, nil)
          {:keep_state, count(data, :errors), reply}
        end
    end
  end

  # The line ----------------------------------------------------------------------------------

  def handle_event(:info, message, state, data) do
    case Connection.handle_message(data.wire, message) do
      {:data, bytes} -> line(state, data, Protocol.handle_bytes(data.protocol, bytes))
      {:closed, reason} -> disconnected(state, data, reason)
      :unknown -> other_info(state, message, data)
    end
  end

  def handle_event(type, content, state, data), do: unexpected(state, type, content, data)

  @impl true
  def terminate(_reason, _state, %{wire: wire}) do
    Connection.close(wire)
    :ok
  end

  defp other_info(_state, {:EXIT, _pid, reason}, _data) when reason != :normal,
    do: {:stop, reason}

  defp other_info(state, message, data), do: unexpected(state, :info, message, data)

  defp unexpected(state, type, content, data) do
    Logger.warning(
      "unexpected #{inspect(type)} #{inspect(content, limit: 10)} in #{inspect(state)}"
    )

    {:keep_state, count(data, :unexpected)}
  end

  # The transport is gone: the protocol halts (down if it was running) and the link is dialled
  # again after the back-off's next wait.
  defp disconnected(state, data, reason) do
    {retry_in, wire} = Connection.lost(data.wire, reason)
    data = %{data | wire: wire}

    line(state, data, Protocol.disconnected(data.protocol, reason), [
      {{:timeout, :connect}, retry_in, :connect}
    ])
  end

  # A result of the protocol: its frames go out, its timers are armed, and its news is handled
  # in order; then what may go now goes (`done/3`).
  defp line(state, data, {protocol, frames, events}, actions \\ []) do
    {news, timers} = Wire.perform(frames, events, data.wire.conn, data.line_meta)
    data = %{data | protocol: protocol}

    {state, data, more} =
      Enum.reduce(news, {state, data, []}, fn event, {state, data, acc} ->
        {state, data, actions} = news(event, state, data)
        {state, data, acc ++ actions}
      end)

    done(state, data, timers ++ actions ++ more)
  end

  defp news(:up, {lun2, activity}, data) do
    Logger.info("VAL II link up")
    lun2 = if lun2 == :down, do: :idle, else: lun2
    data = %{data | gone: nil, wire: Connection.alive(data.wire)}
    {{lun2, activity}, data, []}
  end

  defp news({:down, reason}, _state, data) do
    Logger.warning("VAL II link down: #{inspect(reason)}")
    data = drop_out(data)
    {data, actions} = fail_in_flight(data, {:link_down, reason})

    # A link that restarts by itself (too many failures, a restart asked for) is up again after
    # one start-up exchange: what waits goes then. A transport that is gone may stay gone: what
    # waits fails now, and so does every request until the link is up again.
    {data, more} =
      if transport_gone?(reason),
        do: fail_queued(%{data | gone: reason}, {:link_down, reason}),
        else: {data, []}

    {{:down, :still}, %{data | prompt: nil}, actions ++ more}
  end

  defp news(:peer_restarted, _state, data) do
    Logger.warning("the VAL II controller restarted its link")
    data = drop_out(data)
    {data, actions} = fail_in_flight(data, :peer_restarted)
    # the link starts up again and says :up; the units start afresh then
    {{:down, :still}, %{data | prompt: nil}, actions}
  end

  # The protocol gives data only while running, and the units are :down only between a :down
  # and the next :up: data met while :down would belong to an ended session. Never answered.
  defp news({:data, _bytes}, {:down, _} = state, data), do: {state, count(data, :stale), []}

  defp news({:data, bytes}, state, data) do
    case receive_data(bytes, state, data) do
      {:keep_state, data} -> {state, data, []}
      {:next_state, state, data, actions} -> {state, data, actions}
    end
  end

  # Messages from the logical units ------------------------------------------------------------

  defp receive_data(bytes, state, data) do
    case Message.decode(bytes) do
      {:ok, message} ->
        telemetry_message(data, :in, message, byte_size(bytes))
        receive_message(message, state, count(data, :in))

      {:error, error} ->
        Logger.warning("undecodable VAL message: #{Exception.message(error)}")
        {:keep_state, count(data, :bad)}
    end
  end

  # LUN 2 READ: the monitor prompts for the next command
  defp receive_message(%Message{lun: @lun_monitor, function: :read} = m, {lun2, activity}, data) do
    {data, actions} =
      if lun2 == :busy do
        # a prompt without a response: the command's outcome is unknown
        end_lun2_request(data, {:error, :no_response})
      else
        {data, []}
      end

    {:next_state, {:ready, activity}, %{data | prompt: {m.qualifier, m.text}}, actions}
  end

  # LUN 2 WRITE: the numbered response to the command (or unsolicited monitor output)
  defp receive_message(%Message{lun: @lun_monitor, function: :write} = m, {lun2, activity}, data) do
    data = reply(data, m)

    if lun2 == :busy do
      result = Vws.Links.VAL.parse_response(m.text)
      {data, activity, actions} = response(data, activity, result)
      {:next_state, {:idle, activity}, data, actions}
    else
      Logger.info("VAL II monitor output: #{inspect(m.text)}")
      {:keep_state, data}
    end
  end

  # LUN 3: asynchronous monitor output
  defp receive_message(%Message{lun: @lun_async, function: :write} = m, {lun2, activity}, data) do
    data = reply(data, m)

    Vws.Telemetry.execute([:vws, :val, :async], %{count: 1}, %{
      name: data.name,
      workstation: Vws.Names.id_of(data.name),
      code: m.qualifier,
      text: m.text
    })

    data = %{data | last_async: Enum.take([{m.qualifier, m.text} | data.last_async], @max_async)}
    {data, activity, actions} = async(data, activity, m.qualifier, m.text)
    {:next_state, {lun2, activity}, data, actions}
  end

  # LUN 1: short status
  defp receive_message(%Message{lun: @lun_short_status, function: :write} = m, _state, data) do
    {:keep_state, reply(%{data | short_status: m.text}, m)}
  end

  # any other LUN asking for input gets an empty line, so it is never left blocked
  defp receive_message(%Message{function: :read} = m, _state, data) do
    Logger.warning("VAL II LUN #{m.lun} asks for input: answering an empty line")

    {:keep_state,
     data |> send_message(%Message{lun: m.lun, function: :write}) |> count(:unexpected)}
  end

  defp receive_message(%Message{function: :write} = m, _state, data) do
    Logger.warning("VAL II LUN #{m.lun} output ignored: #{inspect(m.text)}")
    {:keep_state, data |> reply(m) |> count(:unexpected)}
  end

  defp receive_message(%Message{function: :reply} = m, _state, data) do
    # VAL II initiates everything: it never replies to the CEC
    Logger.warning("unexpected REPLY on LUN #{m.lun}")
    {:keep_state, count(data, :unexpected)}
  end

  defp reply(data, %Message{lun: lun, qualifier: q}),
    do: send_message(data, %Message{lun: lun, function: :reply, qualifier: q})

  # The numbered response to the command in flight on LUN 2.
  defp response(data, activity, result) do
    ref = data.lun2_request
    data = %{data | lun2_request: nil}
    request = data.requests[ref]

    case result do
      {:ok, text} when request.wait == :response or request.complete != false ->
        {data, actions} = finish(data, request, {:ok, text})
        {data, activity, actions}

      {:ok, text} ->
        # accepted; the arm is moving (or the program running) until LUN 3 says it is complete
        {put_in(data.requests[ref].response, {:ok, text}), activity, []}

      {:error, _} = error ->
        # refused: nothing moves
        {data, activity} =
          if data.activity_request == ref,
            do: {%{data | activity_request: nil}, :still},
            else: {data, activity}

        {data, actions} = finish(data, request, error)
        {data, activity, actions}
    end
  end

  defp async(data, activity, code, text) do
    ref = data.activity_request
    request = ref && data.requests[ref]

    case {code, request} do
      {complete, %{wait: complete}} ->
        data = %{data | activity_request: nil}

        case request.response do
          {:ok, response} ->
            {data, actions} = finish(data, request, {:ok, response})
            {data, :still, actions}

          nil ->
            # MOTION COMPLETE before the response: the response ends the request
            {put_in(data.requests[ref].complete, true), :still, []}
        end

      {:error, %{}} ->
        error =
          case Vws.Links.VAL.parse_response(text) do
            {:error, {code, _} = e} when is_integer(code) -> e
            _ -> {:async_error, text}
          end

        Logger.warning("VAL II error during #{inspect(request.text)}: #{inspect(text)}")
        data = %{data | activity_request: nil}

        if data.lun2_request == ref do
          # the response is still to come: it is awaited, but the caller learns now
          {data, actions} = reply_early(data, request, {:error, error})
          {data, :still, actions}
        else
          {data, actions} = finish(data, request, {:error, error})
          {data, :still, actions}
        end

      {:error, nil} ->
        Logger.warning("VAL II error: #{inspect(text)}")
        {data, activity, []}

      _ ->
        {data, activity, []}
    end
  end

  # Sending ------------------------------------------------------------------------------------

  # Sends the first queued request that may go now, if any; ends requests whose caller is gone.
  defp dispatch({:ready, activity} = state, data, actions) do
    case next_request(data, activity) do
      nil ->
        {:next_state, state, data, actions}

      {:dead, request} ->
        data = %{data | queue: List.delete(data.queue, request.ref)}
        {data, more} = finish(data, request, {:error, :caller_gone})
        dispatch(state, data, actions ++ more)

      {:go, request} ->
        send_request(state, data, actions, request)
    end
  end

  defp dispatch(state, data, actions), do: {:next_state, state, data, actions}

  # The end of every callback that may change what can go: a queued command goes if it may, and
  # what the units said is given to the protocol.
  defp done(state, data, actions) do
    {:next_state, state, data, actions} = dispatch(state, data, actions)
    {data, line_actions} = flush_out(data)
    # last: the timers of what went out now come after those of the protocol's earlier results
    {:next_state, state, data, actions ++ line_actions}
  end

  defp flush_out(%{out: []} = data), do: {data, []}

  defp flush_out(data) do
    {protocol, frames, events} =
      Enum.reduce(Enum.reverse(data.out), {data.protocol, [], []}, fn bytes, {p, fs, es} ->
        # only while running: never into a later session (what the units say answers this one)
        case Protocol.send(p, bytes, hold: false) do
          {:ok, p, frames, events} ->
            {p, fs ++ frames, es ++ events}

          {:error, reason} ->
            Logger.warning("VAL message not sent: #{inspect(reason)}")
            {p, fs, es}
        end
      end)

    {[], timers} = Wire.perform(frames, events, data.wire.conn, data.line_meta)
    {%{data | out: [], protocol: protocol}, timers}
  end

  defp drop_out(%{out: []} = data), do: data

  defp drop_out(data) do
    Logger.info("VAL II: #{length(data.out)} answer(s) to an ended session not sent")
    %{data | out: []}
  end

  defp send_request({:ready, activity}, data, actions, request) do
    # the command answers this prompt: it carries the prompt's number (see Vws.Links.VAL, "Numbers")
    {number, _text} = data.prompt
    data = %{data | queue: List.delete(data.queue, request.ref), prompt: nil}

    data =
      send_message(data, %Message{
        lun: @lun_monitor,
        function: :write,
        qualifier: number,
        text: request.text
      })

    data = %{data | lun2_request: request.ref}

    if request.wait == :response do
      {:next_state, {:busy, activity}, data, actions}
    else
      {:next_state, {:busy, :moving}, %{data | activity_request: request.ref}, actions}
    end
  end

  defp next_request(data, activity) do
    Enum.find_value(data.queue, fn ref ->
      request = data.requests[ref]
      {pid, _} = request.from

      cond do
        not Process.alive?(pid) -> {:dead, request}
        request.wait != :response and activity == :moving -> nil
        true -> {:go, request}
      end
    end)
  end

  defp send_message(data, message) do
    bytes = Message.encode(message)
    telemetry_message(data, :out, message, IO.iodata_length(bytes))

    count(%{data | out: [bytes | data.out]}, :out)
  end

  # Ending requests ----------------------------------------------------------------------------

  defp end_lun2_request(data, result) do
    ref = data.lun2_request
    data = %{data | lun2_request: nil}
    data = if data.activity_request == ref, do: %{data | activity_request: nil}, else: data
    finish(data, data.requests[ref], result)
  end

  defp fail_in_flight(data, reason) do
    refs = Enum.uniq(Enum.reject([data.lun2_request, data.activity_request], &is_nil/1))
    data = %{data | lun2_request: nil, activity_request: nil}

    Enum.reduce(refs, {data, []}, fn ref, {data, actions} ->
      {data, more} = finish(data, data.requests[ref], {:error, reason})
      {data, actions ++ more}
    end)
  end

  defp transport_gone?(:closed), do: true
  defp transport_gone?({:transport, _}), do: true
  defp transport_gone?(_reason), do: false

  defp fail_queued(data, reason) do
    Enum.reduce(data.queue, {%{data | queue: []}, []}, fn ref, {data, actions} ->
      {data, more} = finish(data, data.requests[ref], {:error, reason})
      {data, actions ++ more}
    end)
  end

  # the caller learns the outcome, but the request stays tracked until its response comes
  defp reply_early(data, request, result) do
    data = put_in(data.requests[request.ref].from, nil)
    data = put_in(data.requests[request.ref].complete, :failed)
    telemetry_finished(data, request, result)

    actions =
      [{{:timeout, {:request, request.ref}}, :cancel}] ++
        if request.from, do: [{:reply, request.from, result}], else: []

    {count(data, :errors), actions}
  end

  defp finish(data, request, result) do
    data = %{data | requests: Map.delete(data.requests, request.ref)}

    if request.complete != :failed, do: telemetry_finished(data, request, result)

    actions =
      [{{:timeout, {:request, request.ref}}, :cancel}] ++
        if request.from && request.complete != :failed,
          do: [{:reply, request.from, result}],
          else: []

    data = count(data, :requests)
    data = if match?({:error, _}, result), do: count(data, :errors), else: data
    {data, actions}
  end

  defp telemetry_finished(data, request, result) do
    Vws.Telemetry.execute(
      [:vws, :val, :request_finished],
      %{duration: System.monotonic_time() - request.started},
      %{
        name: data.name,
        workstation: Vws.Names.id_of(data.name),
        text: request.text,
        result: result
      }
    )
  end

  defp telemetry_message(data, direction, m, bytes) do
    Vws.Telemetry.execute([:vws, :val, :message], %{bytes: bytes}, %{
      name: data.name,
      workstation: Vws.Names.id_of(data.name),
      direction: direction,
      lun: m.lun,
      function: m.function,
      qualifier: m.qualifier,
      text: m.text
    })
  end

  defp count(data, key), do: update_in(data.counts[key], &(&1 + 1))
  defp now, do: System.monotonic_time(:millisecond)
end
