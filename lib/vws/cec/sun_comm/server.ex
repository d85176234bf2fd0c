defmodule Vws.CEC.SunComm.Server do
  @moduledoc false
  # emits the telemetry its core (Vws.CEC.SunComm.Session) returns: the names are checked there
  @telemetry_relay true

  @doc false
  def telemetry_relay?, do: @telemetry_relay
  # SUN_COMM's process, behind the `Vws.CEC.SunComm` facade (which documents the protocol, the
  # states and the options, validated there). The Parser and the transfers are a pure core,
  # `Vws.CEC.SunComm.Session`; this process keeps the link (listener, acceptor, the WC's
  # connection, a tty reopened, the takeover rule), gives the core every line, expired timer and
  # lost link, and carries out what it returns in order (`run/3`): the replies, then the
  # effects, the answer to a request given back to the core at once. The states are the
  # session's modes after `:waiting_to_proceed`, so a transfer's timer is a state timeout.
  #
  # A reply that cannot be sent drops the connection at once (no further reply goes to it); the
  # loss is handled when the result has been carried out, before any other event.

  @behaviour :gen_statem
  require Logger

  alias Vws.CEC.{Events, Mailbox, Partition}
  alias Vws.CEC.SunComm.Session
  alias Vws.Links.Transport
  alias Vws.Codecs.WC.{LineDecoder, Reply}

  @dialogue_length 200

  @impl true
  def callback_mode, do: [:state_functions, :state_enter]

  @impl true
  def init(opts) do
    ws = opts.workstation
    Logger.metadata(workstation: ws, partition: :sun_comm)
    # read and written at every string: found without a Registry look-up (looked up again if new)
    Mailbox.keep_table(ws)
    Process.flag(:trap_exit, true)
    Events.create(ws, :wc_dialogue)
    Events.create(ws, :wc_listening)
    :ok = Events.subscribe(ws, :ok_to_proceed)

    session =
      opts
      |> Map.take([:bcc, :max_program_bytes, :download_timeout, :upload_timeout, :upload_retries])
      |> Keyword.new()
      |> Keyword.put(:last_string, Mailbox.last_string(ws))
      |> Session.new()

    data =
      opts
      |> Map.take([
        :bcc,
        :max_line,
        :tty_retry,
        :partial_line_timeout,
        :allow,
        :takeover_after,
        :takeover_grace,
        :send_timeout
      ])
      |> Map.merge(%{
        workstation: ws,
        endpoint: opts.wc,
        session: session,
        # a newcomer waiting for the current WC's connection to end (takeover grace)
        waiting: nil,
        last_heard: nil,
        listener: nil,
        listening: nil,
        acceptor: nil,
        conn: nil,
        decoder: nil,
        connections: 0,
        dialogue: :queue.new(),
        dialogue_size: 0,
        # the line being answered, {time, text}: it joins the dialogue once its reply is out
        heard: nil
      })

    # OK_TO_PROCEED may have been caused before we subscribed (the workstation causes it just
    # before starting us): then the link opens at once, else when the event comes
    if (Events.count(ws, :ok_to_proceed) || 0) > 0 do
      {:ok, :command, data, [{:next_event, :internal, :open}]}
    else
      {:ok, :waiting_to_proceed, data}
    end
  end

  ## States

  @doc false
  # ON EVENT OK_TO_PROCEED: nothing is read before it.
  def waiting_to_proceed(:enter, _old, _data), do: :keep_state_and_data

  def waiting_to_proceed(:info, {:vws_event, ws, :ok_to_proceed, _}, %{workstation: ws} = data),
    do: {:next_state, :command, data, [{:next_event, :internal, :open}]}

  def waiting_to_proceed(type, content, data),
    do: common(type, content, :waiting_to_proceed, data)

  @doc false
  # Command strings (and status queries) from the WC.
  def command(:enter, _old, _data), do: :keep_state_and_data
  def command(:internal, :open, data), do: open(data)
  def command(type, content, data), do: linked(type, content, :command, data)

  @doc false
  # DOWNLOAD_HP: numbered program lines from the WC.
  def download(:enter, _old, _data), do: :keep_state_and_data
  def download(type, content, data), do: linked(type, content, :download, data)

  @doc false
  # UPLOAD_SUN: numbered program lines to the WC, each answered before the next.
  def upload(:enter, _old, _data), do: :keep_state_and_data
  def upload(type, content, data), do: linked(type, content, :upload, data)

  # Lines and transfer timers go to the session.
  defp linked(:internal, {:line, line}, state, data) do
    # into the dialogue just after the reply to it went out, still before that reply: an answer
    # does not wait for the dialogue's subscribers
    data = %{data | heard: {now_ms(), dialogue_text(line)}}
    step(state, data, Session.handle_line(data.session, line, ctx()))
  end

  defp linked(:state_timeout, name, state, data),
    do: step(state, data, Session.handle_timeout(data.session, name, ctx()))

  defp linked(type, content, state, data), do: common(type, content, state, data)

  defp dialogue_text({:error, error}), do: "<#{Exception.message(error)}>"
  defp dialogue_text(line), do: line

  ## Events of every state

  defp common({:call, from}, :info, state, data) do
    info = %{
      workstation: data.workstation,
      endpoint: data.endpoint,
      listening: data.listening,
      ok_to_proceed: state != :waiting_to_proceed,
      peer: data.conn && Transport.peer(data.conn),
      mode: Session.mode_name(data.session),
      transfer: Session.transfer_info(data.session),
      counters: Map.put(Session.counters(data.session), :connections, data.connections)
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  # A command from this node's operator (`Vws.Ops.Web.Command`), not from the WC
  # (`Session.local_command/5`): :ok (dispatched; the status tells the rest) or {:error, words}.
  defp common({:call, from}, {:local_command, _, _, _}, :waiting_to_proceed, _data),
    do:
      {:keep_state_and_data, [{:reply, from, {:error, "NOT READY (WAITING FOR OK TO PROCEED)"}}]}

  defp common({:call, from}, {:local_command, letter, number, text}, state, data) do
    {answer, result} = Session.local_command(data.session, letter, number, text, ctx())
    step(state, data, result, [{:reply, from, answer}])
  end

  defp common({:call, from}, :dialogue, _state, data),
    do: {:keep_state_and_data, [{:reply, from, :queue.to_list(data.dialogue)}]}

  defp common(:info, {:vws_event, _ws, :ok_to_proceed, _}, _state, _data),
    do: :keep_state_and_data

  defp common(:info, {:wc_accepted, conn}, state, data) do
    cond do
      data.conn == nil or silent_ms(data) >= data.takeover_after ->
        take_link(state, data, conn)

      data.waiting != nil ->
        # one newcomer waits at a time; a second one is refused at once
        {:keep_state, refuse(data, conn)}

      true ->
        # the current connection may have ended already, its close still on its way to us:
        # the newcomer waits (unread) a moment for it, and is refused only if it does not come
        {:keep_state, %{data | waiting: conn},
         [{{:timeout, :takeover_grace}, data.takeover_grace, conn}]}
    end
  end

  defp common({:timeout, :takeover_grace}, conn, _state, %{waiting: conn} = data),
    do: {:keep_state, refuse(%{data | waiting: nil}, conn)}

  defp common({:timeout, :takeover_grace}, _stale, _state, _data), do: :keep_state_and_data

  defp common({:timeout, :reopen_tty}, _, state, data), do: open_tty(state, data)

  defp common({:timeout, :partial_line}, _, state, data) do
    # the end of a line never came: its CR LF was lost or damaged on the line
    data = %{data | decoder: data.decoder && LineDecoder.new(max_line: data.max_line)}
    data = record(data, :in, "<unfinished line dropped after #{data.partial_line_timeout} ms>")
    step(state, data, Session.unfinished_line(data.session))
  end

  defp common(:internal, {:link_lost, peer, why}, state, data),
    do: link_lost(state, data, peer, why, [])

  defp common(:internal, :read_more, _state, data) do
    if data.conn, do: Transport.activate(data.conn)
    {:keep_state_and_data, [watch_partial_line(data)]}
  end

  defp common(:info, {:EXIT, pid, reason}, _state, %{acceptor: pid}),
    do: {:stop, {:acceptor_down, reason}}

  defp common(:info, {:EXIT, _pid, _reason}, _state, _data), do: :keep_state_and_data

  defp common(:info, msg, _state, %{conn: conn} = data) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        {lines, decoder} = LineDecoder.feed(data.decoder, bytes)
        data = %{data | decoder: decoder, last_heard: now_ms()}

        {:keep_state, data,
         Enum.map(lines, &{:next_event, :internal, {:line, &1}}) ++
           [{:next_event, :internal, :read_more}]}

      :closed ->
        {:keep_state_and_data,
         [{:next_event, :internal, {:link_lost, Transport.peer(conn), "closed"}}]}

      {:error, reason} ->
        {:keep_state_and_data,
         [{:next_event, :internal, {:link_lost, Transport.peer(conn), inspect(reason)}}]}

      :unknown ->
        Logger.debug("SUN_COMM ignored #{inspect(msg, limit: 10)}")
        :keep_state_and_data
    end
  end

  defp common(type, content, state, _data) do
    Logger.debug("SUN_COMM ignored #{inspect({type, content}, limit: 10)} in #{state}")
    :keep_state_and_data
  end

  @impl true
  def terminate(_reason, _state, data) do
    if data.conn, do: Transport.close(data.conn)
    if data.waiting, do: Transport.close(data.waiting)
    if data.listener, do: Transport.close_listener(data.listener)
    :ok
  end

  ## Carrying out the session's results

  # A result of the session carried out; the callback's answer, in the session's mode.
  defp step(state, data, result, actions \\ []) do
    case run(data, result, {actions, nil}) do
      {data, actions, nil} ->
        data = record_heard(data)
        {:next_state, next_state(state, data), data, actions}

      {data, actions, {peer, why}} ->
        link_lost(state, record_heard(data), peer, why, actions)
    end
  end

  defp next_state(:waiting_to_proceed, _data), do: :waiting_to_proceed
  defp next_state(_state, data), do: Session.mode(data.session)

  # The replies, then the effects in order; a request (always the last effect) is answered
  # into the session at once and what that returns is carried out in turn. `lost`: the peer
  # and reason of a connection a reply could not be sent on.
  defp run(data, {session, replies, effects}, {actions, lost}) do
    {data, lost} = Enum.reduce(replies, {%{data | session: session}, lost}, &send_reply/2)
    {actions, answer} = Enum.reduce(effects, {actions, nil}, &perform(&1, &2, data))

    case answer do
      nil -> {data, actions, lost}
      {:answer, a} -> run(data, Session.handle_result(data.session, a, ctx()), {actions, lost})
    end
  end

  @requests [:journal, :dispatch, :claim, :read_status, :read_nc_up, :store_program]

  defp perform({:timer, name, ms}, {actions, nil}, _data),
    do: {actions ++ [{:state_timeout, ms, name}], nil}

  defp perform(request, {actions, nil}, data) when elem(request, 0) in @requests,
    do: {actions, {:answer, answer(request, data.workstation)}}

  defp perform(effect, {actions, nil}, data) do
    carry_out(effect, data.workstation)
    {actions, nil}
  end

  defp carry_out({:log, level, message}, _ws), do: Logger.log(level, message)

  defp carry_out({:telemetry, event, measurements, metadata}, ws),
    do: Vws.Telemetry.execute(event, measurements, Map.put(metadata, :workstation, ws))

  defp carry_out({:remember_string, sequence, line}, ws),
    do: Mailbox.put_last_string(ws, sequence, line)

  defp carry_out({:status, {:unknown, letter}, number, status}, ws),
    do: Mailbox.put_unknown_status(ws, letter, number, status)

  defp carry_out({:status, set, number, status}, ws),
    do: Mailbox.put_status(ws, set, number, status)

  # A transfer's command ends here unless something ended it first (MONARCH restarted while
  # SUN_COMM carried it out: `ERROR INTERRUPTED BY PARTITION RESTART`); only an end that was
  # written is reported.
  defp carry_out({:finish, number, status}, ws) do
    with :ok <- Mailbox.finish(ws, :monarch, number, status) do
      Vws.Telemetry.execute([:vws, :partition, :command_finished], %{duration: 0}, %{
        workstation: ws,
        partition: :monarch,
        command: number,
        status: status
      })
    end
  end

  defp answer({:journal, record}, ws), do: Vws.CEC.Journal.record(Mailbox.table(ws), record)
  defp answer({:dispatch, set, n, text}, ws), do: Partition.dispatch(ws, set, n, text)
  defp answer({:claim, set, n, text}, ws), do: Mailbox.dispatch(ws, set, n, text)
  defp answer({:read_status, name}, ws), do: Vws.CEC.SunComm.Status.answer(ws, name)
  defp answer({:read_nc_up}, ws), do: Mailbox.nc_up(ws)

  # Into the program library first (issue 18), when the workstation has one; then the NC file,
  # which the journal keeps as a reference to that version when the version gives these very
  # lines back — one durable copy of the program, not two.
  defp answer({:store_program, lines}, ws) do
    case Vws.CEC.Library.store_download(ws, lines) do
      {:ok, v} -> Mailbox.put_nc_file(ws, lines, library_version(v, lines))
      :ok -> Mailbox.put_nc_file(ws, lines)
      {:error, _} = error -> error
    end
  end

  defp library_version(v, lines) do
    alias Vws.Links.DNC.Program

    if v.digest != nil and Program.from_text(Program.to_text(lines)) == lines,
      do: {:library, v.name, v.version, v.digest}
  end

  defp send_reply(_reply, {%{conn: nil} = data, lost}), do: {data, lost}

  defp send_reply(reply, {data, lost}) do
    bytes = reply |> Reply.encode(bcc: data.bcc) |> IO.iodata_to_binary()
    sent = Transport.send(data.conn, bytes)
    data = record_heard(data)

    case sent do
      :ok ->
        telemetry(data, :reply_sent, %{bytes: byte_size(bytes)}, %{kind: reply_kind(reply)})
        # (every reply ends with its one CR LF)
        {record(data, :out, binary_part(bytes, 0, byte_size(bytes) - 2)), lost}

      {:error, reason} ->
        # a WC that does not read (send_timeout) or is gone: drop it rather than wait on it
        peer = Transport.peer(data.conn)
        Transport.close(data.conn)
        {%{data | conn: nil}, {peer, "reply not sent: #{inspect(reason)}"}}
    end
  end

  defp reply_kind(reply) when is_atom(reply), do: reply
  defp reply_kind(reply) when is_tuple(reply), do: elem(reply, 0)

  ## The link

  defp open(%{endpoint: nil}), do: :keep_state_and_data

  defp open(data) do
    endpoint = Vws.Links.Endpoint.parse!(data.endpoint)

    if endpoint.kind == :tty do
      open_tty(:command, data)
    else
      case Transport.listen(endpoint, send_timeout: data.send_timeout) do
        {:ok, listener} ->
          acceptor = Transport.start_acceptor(listener, self(), :wc_accepted, allow: data.allow)
          bound = Transport.listener_endpoint(listener)

          Logger.info(
            "SUN_COMM listening for the WC on #{bound} (#{Vws.Links.Transport.Policy.describe(data.allow)})"
          )

          :ok = Events.cause(data.workstation, :wc_listening, bound)
          {:keep_state, %{data | listener: listener, listening: bound, acceptor: acceptor}}

        {:error, reason} ->
          {:stop, {:cannot_listen, data.endpoint, reason}}
      end
    end
  end

  defp open_tty(state, data) do
    case Transport.connect(data.endpoint) do
      {:ok, conn} ->
        Vws.LogLimit.clear(:wc_tty, "WC tty #{data.endpoint} open")
        :ok = Events.cause(data.workstation, :wc_listening, conn.endpoint)
        take_link(state, %{data | listening: conn.endpoint}, conn)

      {:error, reason} ->
        # once, not at every try (once a second)
        Vws.LogLimit.warning(
          :wc_tty,
          "cannot open the WC tty #{data.endpoint}: #{inspect(reason)}; retrying",
          :error
        )

        {:keep_state_and_data, [{{:timeout, :reopen_tty}, data.tty_retry, :reopen}]}
    end
  end

  # A new connection becomes the WC's link; the one it replaces (and any transfer on it) ends.
  defp take_link(state, data, conn, actions \\ []) do
    {data, actions, nil} =
      run(data, Session.link_lost(data.session, "WC LINK TAKEN OVER"), {actions, nil})

    if old = data.conn do
      Logger.warning(
        "WC connection from #{Transport.peer(conn)} takes over from #{Transport.peer(old)}, which is closed"
      )

      Transport.close(old)

      telemetry(data, :wc_disconnected, %{count: 1}, %{
        peer: Transport.peer(old),
        reason: :taken_over
      })
    end

    Logger.info("WC connected: #{Transport.peer(conn)}")
    telemetry(data, :wc_connected, %{count: 1}, %{peer: Transport.peer(conn)})
    Transport.activate(conn)

    data = %{
      data
      | conn: conn,
        last_heard: now_ms(),
        decoder: LineDecoder.new(max_line: data.max_line),
        connections: data.connections + 1
    }

    # the new connection's first bytes start their own line
    {:next_state, next_state(state, data), data,
     actions ++ [{{:timeout, :partial_line}, :cancel}]}
  end

  defp silent_ms(data), do: now_ms() - data.last_heard

  defp refuse(data, conn) do
    Logger.warning(
      "WC connection from #{Transport.peer(conn)} refused: the WC on #{Transport.peer(data.conn)} " <>
        "was heard #{silent_ms(data)} ms ago (a takeover needs #{data.takeover_after} ms of silence)"
    )

    telemetry(data, :wc_refused, %{count: 1}, %{
      peer: Transport.peer(conn),
      current: Transport.peer(data.conn)
    })

    Transport.close(conn)
    data
  end

  defp link_lost(state, data, peer, why, actions) do
    # the WC closing its connection is how a WC ends a session: news, not a warning
    if why == "closed",
      do: Logger.info("WC link closed by the WC"),
      else: Logger.warning("WC link lost (#{why})")

    telemetry(data, :wc_disconnected, %{count: 1}, %{peer: peer, reason: why})
    data = %{data | conn: nil, decoder: nil}

    # a tty: open it again
    reopen =
      if data.listener == nil and data.endpoint,
        do: [{{:timeout, :reopen_tty}, data.tty_retry, :reopen}],
        else: []

    actions = actions ++ [{{:timeout, :partial_line}, :cancel} | reopen]

    {data, actions, nil} =
      run(data, Session.link_lost(data.session, "WC LINK LOST"), {actions, nil})

    case data.waiting do
      nil ->
        {:next_state, next_state(state, data), data, actions}

      conn ->
        # the current WC is gone: a newcomer waiting for that takes the link now
        actions = actions ++ [{{:timeout, :takeover_grace}, :cancel}]
        take_link(state, %{data | waiting: nil}, conn, actions)
    end
  end

  # Bytes of an unfinished line start (or restart) the inter-character timer; a line whose end
  # does not follow within `partial_line_timeout` is dropped and answered `E` (a WC waiting on
  # the answer to a program line would otherwise wait for ever, and may not send it again
  # unasked: a line whose `A` was lost would be stored twice).
  defp watch_partial_line(%{decoder: decoder} = data) do
    if decoder != nil and LineDecoder.buffered(decoder) > 0,
      do: {{:timeout, :partial_line}, data.partial_line_timeout, :unfinished},
      else: {{:timeout, :partial_line}, :cancel}
  end

  ## Dialogue, telemetry

  defp record_heard(%{heard: nil} = data), do: data
  defp record_heard(%{heard: {at, line}} = data), do: record(%{data | heard: nil}, :in, line, at)

  defp record(data, direction, line, at \\ now_ms()) do
    entry = {at, direction, line}
    Events.cause(data.workstation, :wc_dialogue, entry)
    queue = :queue.in(entry, data.dialogue)

    if data.dialogue_size >= @dialogue_length do
      %{data | dialogue: :queue.drop(queue)}
    else
      %{data | dialogue: queue, dialogue_size: data.dialogue_size + 1}
    end
  end

  defp telemetry(data, event, measurements, metadata) do
    Vws.Telemetry.execute(
      [:vws, :sun_comm, event],
      measurements,
      Map.put(metadata, :workstation, data.workstation)
    )
  end

  defp ctx, do: %{now: now_ms()}
  defp now_ms, do: System.monotonic_time(:millisecond)
end
