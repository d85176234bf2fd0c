defmodule Vws.CEC.SunComm.Server do
  @moduledoc false
  # SUN_COMM's process, behind the `Vws.CEC.SunComm` facade (which documents the protocol, the
  # states and the options, validated there). States are the modes: `:waiting_to_proceed`,
  # `:command`, `:download`, `:upload`; the link is data beside them.
  #
  # The functions below the state callbacks take and return the data; those that may end or
  # start a transfer return `{state, data, actions}`, which `step/1` turns into the callback's
  # result. A reply that cannot be sent drops the connection at once (no further reply goes to
  # it) and inserts `{:link_lost, peer, why}`, handled next, before any other event: that is
  # where a transfer the loss interrupts ends.

  @behaviour :gen_statem
  require Logger

  alias Vws.CEC.{Events, Mailbox}
  alias Vws.Links.Transport
  alias Vws.Codecs.WC.{Command, CommandString, LineDecoder, ProgramCRC, Reply}

  @dialogue_length 200

  @impl true
  def callback_mode, do: [:state_functions, :state_enter]

  @impl true
  def init(opts) do
    ws = opts.workstation
    Logger.metadata(workstation: ws, partition: :sun_comm)
    Process.flag(:trap_exit, true)
    Events.create(ws, :wc_dialogue)
    Events.create(ws, :wc_listening)
    :ok = Events.subscribe(ws, :ok_to_proceed)

    data =
      opts
      |> Map.take([
        :bcc,
        :max_line,
        :download_timeout,
        :upload_timeout,
        :upload_retries,
        :max_program_bytes,
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
        # a newcomer waiting for the current WC's connection to end (takeover grace)
        waiting: nil,
        last_heard: nil,
        listener: nil,
        listening: nil,
        acceptor: nil,
        conn: nil,
        decoder: nil,
        # the download or upload under way (in those states), else nil
        transfer: nil,
        # the closing line of the last download and its answer: a resend of it after the
        # transfer ended (its answer was damaged) is answered again
        last_closing: nil,
        # events to insert after the current one (a link lost while replying)
        pending: [],
        dialogue: :queue.new(),
        dialogue_size: 0,
        counters: %{
          strings: 0,
          naks: 0,
          retransmissions: 0,
          rules_broken: 0,
          status_answers: 0,
          connections: 0,
          lines_in: 0,
          lines_out: 0,
          lines_again: 0
        }
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

  def command(:internal, {:line, {:error, error}}, data), do: damaged_line(:command, error, data)

  def command(:internal, {:line, line}, data),
    do: step(command_line(line, record(data, :in, line)))

  def command(type, content, data), do: common(type, content, :command, data)

  @doc false
  # DOWNLOAD_HP: numbered program lines from the WC.
  def download(:enter, _old, _data), do: :keep_state_and_data

  def download(:internal, {:line, {:error, error}}, data),
    do: damaged_line(:download, error, data)

  def download(:internal, {:line, line}, data) do
    data = record(data, :in, line)

    case string_during_transfer(line, data) do
      {:ok, cs} -> step(command_string_in_transfer(cs, line, :download, data))
      _no_string -> step(download_line(line, data))
    end
  end

  def download(:state_timeout, :no_line, %{transfer: d} = data),
    do:
      step(
        {:command,
         end_transfer(data, d.number, {:error, "DOWNLOAD STALLED AFTER #{d.count} LINES"}), []}
      )

  def download(type, content, data), do: common(type, content, :download, data)

  @doc false
  # UPLOAD_SUN: numbered program lines to the WC, each answered before the next.
  def upload(:enter, _old, _data), do: :keep_state_and_data

  def upload(:internal, {:line, {:error, error}}, data), do: damaged_line(:upload, error, data)

  def upload(:internal, {:line, line}, data) do
    data = record(data, :in, line)

    case string_during_transfer(line, data) do
      {:ok, cs} -> step(command_string_in_transfer(cs, line, :upload, data))
      _no_string -> step(upload_answer(line, data))
    end
  end

  def upload(:state_timeout, :no_answer, data), do: step(resend_upload_line(data))

  def upload(type, content, data), do: common(type, content, :upload, data)

  # A line the decoder could not take (too long): answered E, the state unchanged.
  defp damaged_line(state, error, data),
    do:
      step({state, reject(record(data, :in, "<#{Exception.message(error)}>"), error.reason), []})

  ## Events of every state

  defp common({:call, from}, :info, state, data) do
    info = %{
      workstation: data.workstation,
      endpoint: data.endpoint,
      listening: data.listening,
      ok_to_proceed: state != :waiting_to_proceed,
      peer: data.conn && Transport.peer(data.conn),
      mode: mode_name(state, data.transfer),
      transfer: transfer_info(state, data.transfer),
      counters: data.counters
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  # A command from this node's operator (`Vws.Ops.Web.Command`), not from the WC: the same rules
  # of the Parser for one command, the same dispatch (interlocks in its partition, the journal
  # in Mailbox.dispatch/4) as a WC string's command. Nothing goes on the WC link, and the WC's
  # last string (rule 4) is untouched. Transfers with the WC (DOWNLOAD_HP, UPLOAD_SUN) are not
  # for it. Answers :ok (dispatched; the status tells the rest) or {:error, words}.
  defp common({:call, from}, {:local_command, letter, number, text}, state, data) do
    set = Command.set_for_letter(letter)

    {data, answer} =
      cond do
        state == :waiting_to_proceed ->
          {data, {:error, "NOT READY (WAITING FOR OK TO PROCEED)"}}

        set not in Mailbox.partitions() ->
          {data, {:error, "UNKNOWN COMMAND SET #{letter}"}}

        set == :monarch and Vws.Codecs.Commands.transfer(text) in [:download_hp, :upload_sun] ->
          {data, {:error, "TRANSFER WITH THE WC ONLY"}}

        true ->
          Logger.info("operator command #{letter}#{Command.pad4(number)} #{text}")
          {data, nil} = dispatch(%{set: set, number: number, text: text}, data)
          {%{data | counters: Map.update(data.counters, :operator_commands, 1, &(&1 + 1))}, :ok}
      end

    {:keep_state, data, [{:reply, from, answer}]}
  end

  defp common({:call, from}, :dialogue, _state, data),
    do: {:keep_state_and_data, [{:reply, from, :queue.to_list(data.dialogue)}]}

  defp common(:info, {:vws_event, _ws, :ok_to_proceed, _}, _state, _data),
    do: :keep_state_and_data

  defp common(:info, {:wc_accepted, conn}, state, data) do
    cond do
      data.conn == nil or silent_ms(data) >= data.takeover_after ->
        step(take_link(state, data, conn))

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

  defp common({:timeout, :reopen_tty}, _, state, data), do: step(open_tty(state, data))

  defp common({:timeout, :partial_line}, _, state, data) do
    # the end of a line never came: its CR LF was lost or damaged on the line
    data = %{data | decoder: data.decoder && LineDecoder.new(max_line: data.max_line)}
    data = record(data, :in, "<unfinished line dropped after #{data.partial_line_timeout} ms>")
    data = if state == :upload, do: data, else: reject(data, :unfinished_line)
    step({state, data, []})
  end

  defp common(:internal, {:link_lost, peer, why}, state, data),
    do: step(link_lost(state, data, peer, why))

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

  # `{state, data, actions}` → the callback's result, with the events a lost link inserted.
  defp step({state, data, actions}) do
    {:next_state, state, %{data | pending: []}, actions ++ Enum.reverse(data.pending)}
  end

  ## The link

  defp open(%{endpoint: nil}), do: :keep_state_and_data

  defp open(data) do
    endpoint = Vws.Links.Endpoint.parse!(data.endpoint)

    if endpoint.kind == :tty do
      step(open_tty(:command, data))
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
        {state, data, actions} = take_link(state, data, conn)
        :ok = Events.cause(data.workstation, :wc_listening, conn.endpoint)
        {state, %{data | listening: conn.endpoint}, actions}

      {:error, reason} ->
        # once, not at every try (once a second)
        Vws.LogLimit.warning(
          :wc_tty,
          "cannot open the WC tty #{data.endpoint}: #{inspect(reason)}; retrying",
          :error
        )

        {state, data, [{{:timeout, :reopen_tty}, data.tty_retry, :reopen}]}
    end
  end

  # A new connection becomes the WC's link; the one it replaces (and any transfer on it) ends.
  defp take_link(state, data, conn) do
    data =
      if data.conn do
        Logger.warning(
          "WC connection from #{Transport.peer(conn)} takes over from #{Transport.peer(data.conn)}, which is closed"
        )

        old = data.conn
        data = abort_transfer(data, "WC LINK TAKEN OVER")
        Transport.close(old)

        telemetry(data, :wc_disconnected, %{count: 1}, %{
          peer: Transport.peer(old),
          reason: :taken_over
        })

        data
      else
        abort_transfer(data, "WC LINK TAKEN OVER")
      end

    Logger.info("WC connected: #{Transport.peer(conn)}")
    telemetry(data, :wc_connected, %{count: 1}, %{peer: Transport.peer(conn)})
    Transport.activate(conn)

    data = %{
      data
      | conn: conn,
        last_heard: now_ms(),
        decoder: LineDecoder.new(max_line: data.max_line),
        counters: bump(data.counters, :connections)
    }

    # the new connection's first bytes start their own line
    {next_mode(state, data), data, [{{:timeout, :partial_line}, :cancel}]}
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

  defp link_lost(state, data, peer, why) do
    # the WC closing its connection is how a WC ends a session: news, not a warning
    if why == "closed",
      do: Logger.info("WC link closed by the WC"),
      else: Logger.warning("WC link lost (#{why})")

    telemetry(data, :wc_disconnected, %{count: 1}, %{peer: peer, reason: why})
    data = abort_transfer(data, "WC LINK LOST")
    data = %{data | conn: nil, decoder: nil}

    reopen =
      if data.listener == nil and data.endpoint do
        # a tty: open it again
        [{{:timeout, :reopen_tty}, data.tty_retry, :reopen}]
      else
        []
      end

    actions = [{{:timeout, :partial_line}, :cancel} | reopen]

    case data.waiting do
      nil ->
        {next_mode(state, data), data, actions}

      conn ->
        # the current WC is gone: a newcomer waiting for that takes the link now
        {state, data, more} = take_link(state, %{data | waiting: nil}, conn)

        {state, data, actions ++ [{{:timeout, :takeover_grace}, :cancel} | more]}
    end
  end

  # A transfer that ended (its data gone) leaves its state for :command.
  defp next_mode(:waiting_to_proceed, _data), do: :waiting_to_proceed
  defp next_mode(_state, %{transfer: nil}), do: :command
  defp next_mode(state, _data), do: state

  # Bytes of an unfinished line start (or restart) the inter-character timer; a line whose end
  # does not follow within `partial_line_timeout` is dropped and answered `E` (a WC waiting on
  # the answer to a program line would otherwise wait for ever, and may not send it again
  # unasked: a line whose `A` was lost would be stored twice).
  defp watch_partial_line(%{decoder: decoder} = data) do
    if decoder != nil and LineDecoder.buffered(decoder) > 0,
      do: {{:timeout, :partial_line}, data.partial_line_timeout, :unfinished},
      else: {{:timeout, :partial_line}, :cancel}
  end

  ## Lines in

  # An intact command string during a program transfer: the WC is not in the transfer. Decoded
  # here once; the decoded string is what is handled from here on.
  defp string_during_transfer("*" <> _ = line, data),
    do: CommandString.decode(line, bcc: data.bcc)

  defp string_during_transfer(_line, _data), do: :no

  # The string that began the transfer, again: its acknowledgement was lost and the WC is
  # still waiting for it, so it is acknowledged again and the transfer begins afresh from its
  # first line (the WC sends or takes the program only after the acknowledgement). A status
  # query during an upload is answered and the upload goes on: it runs nothing, and a WC that
  # has taken the closing line asks its command's status while its answer reached us damaged —
  # the closing line goes again and it answers again. Any other string (and a status query
  # during a download, where the WC is the sender): the WC gave the transfer up; it ends
  # ERROR and the string is handled as usual.
  defp command_string_in_transfer(cs, line, kind, data) do
    cond do
      Mailbox.last_string(data.workstation) == {cs.sequence, line} ->
        restart_transfer(cs, kind, data)

      kind == :upload and status_string?(cs) ->
        {data, nil} = accept_string(cs, line, data)
        {:upload, data, []}

      true ->
        Logger.warning("string #{cs.sequence} during #{kind}: the WC left the transfer")
        string_received(cs, line, abort_transfer(data, "COMMAND STRING FROM THE WC"))
    end
  end

  defp restart_transfer(cs, kind, data) do
    Logger.info(
      "string #{cs.sequence} again during #{kind}: acknowledged again, transfer restarted"
    )

    telemetry(data, :retransmission, %{count: 1}, %{sequence: cs.sequence})
    data = reply(%{data | counters: bump(data.counters, :retransmissions)}, {:ack, cs.sequence})
    start_transfer(again(kind, data.transfer), data)
  end

  defp reject(data, reason) do
    telemetry(data, :string_rejected, %{bytes: 0}, %{reason: reason})
    %{reply(data, :nak) | counters: bump(data.counters, :naks)}
  end

  defp command_line("", data), do: {:command, reject(data, :empty_line), []}

  defp command_line(line, %{last_closing: {line, answer}} = data) do
    Logger.info("the closing line of the last download again: answered again")
    {:command, %{reply(data, answer) | counters: bump(data.counters, :lines_again)}, []}
  end

  defp command_line(line, data) do
    case CommandString.decode(line, bcc: data.bcc) do
      {:error, error} -> {:command, reject(%{data | last_closing: nil}, error.reason), []}
      {:ok, cs} -> string_received(cs, line, data)
    end
  end

  # A decoded string, in :command (or just back in it from a transfer the string ended).
  defp string_received(cs, line, data) do
    data = %{data | last_closing: nil, counters: bump(data.counters, :strings)}

    telemetry(data, :string_received, %{bytes: byte_size(line)}, %{
      sequence: cs.sequence,
      commands: length(cs.commands)
    })

    case accept_string(cs, line, data) do
      {data, nil} -> {:command, data, []}
      {data, transfer} -> start_transfer(transfer, data)
    end
  end

  # The Parser's rules, then the commands dispatched. Returns the data and the transfer the
  # string begins (`{:download, number, expected}`, `{:upload, number}`), or nil.
  defp accept_string(cs, line, data) do
    ws = data.workstation

    cond do
      status_string?(cs) ->
        # status strings are not remembered for rule 4: answering one twice is harmless, and a
        # status poll between a lost acknowledgement and its resend must not hide the resend
        [status] = cs.commands
        text = Vws.CEC.SunComm.Status.answer(ws, status.text)
        data = %{data | counters: bump(data.counters, :status_answers)}
        {reply(data, {:status, status.number, text}), nil}

      Mailbox.last_string(ws) == {cs.sequence, line} ->
        Logger.info(
          "string #{cs.sequence} is a retransmission: acknowledged again, nothing executed"
        )

        telemetry(data, :retransmission, %{count: 1}, %{sequence: cs.sequence})
        data = %{data | counters: bump(data.counters, :retransmissions)}
        {reply(data, {:ack, cs.sequence}), nil}

      journal_string(ws, cs, line) != :ok ->
        # not durable, so not acknowledged: the WC sends it again
        {reject(data, :journal_unavailable), nil}

      broken = broken_rule(cs) ->
        Mailbox.put_last_string(ws, cs.sequence, line)
        data = reply(data, {:ack, cs.sequence})
        Logger.warning("string #{cs.sequence} breaks a rule (#{broken}): nothing in it runs")
        telemetry(data, :rule_broken, %{count: 1}, %{sequence: cs.sequence, rule: broken})

        for %{set: set, number: n} <- cs.commands do
          case set do
            {:unknown, letter} -> Mailbox.put_unknown_status(ws, letter, n, {:error, broken})
            :ack -> :ok
            set -> Mailbox.put_status(ws, set, n, {:error, broken})
          end
        end

        {%{data | counters: bump(data.counters, :rules_broken)}, nil}

      true ->
        Mailbox.put_last_string(ws, cs.sequence, line)
        data = reply(data, {:ack, cs.sequence})
        # rule 1: one Monarch command at most, so one transfer at most
        Enum.reduce(cs.commands, {data, nil}, fn command, {data, transfer} ->
          case dispatch(command, data) do
            {data, nil} -> {data, transfer}
            {data, started} -> {data, started}
          end
        end)
    end
  end

  defp journal_string(ws, cs, line) do
    commands =
      for %{set: set, number: n} <- cs.commands, set in Mailbox.partitions(), do: {set, n}

    Vws.CEC.Journal.record(Mailbox.table(ws), {:string, cs.sequence, line, commands})
  end

  defp status_string?(%{commands: [%{set: :status}]}), do: true
  defp status_string?(_), do: false

  defp broken_rule(cs) do
    letters = Enum.map(cs.commands, & &1.letter)

    cond do
      unknown = Enum.find(cs.commands, &match?({:unknown, _}, &1.set)) ->
        "UNKNOWN COMMAND SET #{unknown.letter}"

      Enum.any?(cs.commands, &(&1.set == :status)) ->
        "RULE 2 STATUS COMMAND NOT ALONE"

      dup = Enum.find(letters, &(Enum.count(letters, fn l -> l == &1 end) > 1)) ->
        "RULE 1 SET #{dup} REPEATED"

      true ->
        nil
    end
  end

  # One command to its partition (CMD_IN + CAUSE EVENT), or — DOWNLOAD_HP, UPLOAD_SUN — the
  # transfer SUN_COMM carries out itself: `{data, nil | {:download, number, expected} |
  # {:upload, number}}`.
  defp dispatch(%{set: :ack} = command, data) do
    Logger.debug("acknowledgement command #{command.number} #{command.text}")
    {data, nil}
  end

  defp dispatch(%{set: set, number: number, text: text}, data) do
    ws = data.workstation

    case Mailbox.dispatch(ws, set, number, text) do
      {:busy, previous} ->
        Logger.warning("#{set} command #{number} refused: command #{previous} still in flight")
        Mailbox.put_status(ws, set, number, {:error, "BUSY #{Command.pad4(previous)}"})
        {data, nil}

      {:error, _journal_write_failed} ->
        # not durable, so not run: its status says so (Mailbox.dispatch/4)
        {data, nil}

      :ok ->
        Vws.Telemetry.execute([:vws, :partition, :command_dispatched], %{count: 1}, %{
          workstation: ws,
          partition: set,
          command: number,
          text: text
        })

        # the two transfers SUN_COMM carries out are recognised here; every other command is
        # parsed once, by its partition
        case set == :monarch && Vws.Codecs.Commands.transfer(text) do
          # the WC names the program's CRC, or not (the seed's form), or names it badly: the
          # program's lines follow in every case, and the check is made at its end
          :download_hp ->
            {data, {:download, number, nil}}

          {:download_hp, crc} ->
            {data, {:download, number, crc}}

          {:error, why} ->
            {data, {:download, number, {:error, why}}}

          :upload_sun ->
            {data, {:upload, number}}

          _ ->
            :ok = Events.cause(ws, set, number)
            {data, nil}
        end
    end
  end

  ## Transfers

  # `expected`: the program's CRC the WC named, nil (none named) or `{:error, why}` (named
  # badly); `crc` the CRC of the lines stored so far (PROTOCOLS.md §1 "Whole-program check")
  defp start_transfer({:download, number, expected}, data) do
    Logger.info("DOWNLOAD_HP #{number}: reading program lines from the WC")

    d = %{
      kind: :download,
      number: number,
      expected: expected,
      lines: [],
      count: 0,
      bytes: 0,
      crc: 0,
      started: now_ms()
    }

    {:download, %{data | transfer: d}, [download_timer(data)]}
  end

  defp start_transfer({:upload, number}, data) do
    case Mailbox.nc_up(data.workstation) do
      [] ->
        Mailbox.finish(data.workstation, :monarch, number, {:error, "NO UPLOADED PROGRAM"})
        {:command, %{data | transfer: nil}, []}

      lines ->
        Logger.info("UPLOAD_SUN #{number}: sending #{length(lines)} lines to the WC")

        u = %{
          kind: :upload,
          number: number,
          lines: lines,
          sent: 0,
          retries: 0,
          started: now_ms(),
          total: length(lines),
          bytes: 0,
          total_bytes: Enum.reduce(lines, 0, &(byte_size(&1) + 1 + &2)),
          crc: ProgramCRC.compute(lines)
        }

        send_upload_line(%{data | transfer: u})
    end
  end

  # the transfer a resent string begins again
  defp again(:download, d), do: {:download, d.number, d.expected}
  defp again(:upload, u), do: {:upload, u.number}

  defp download_timer(data), do: {:state_timeout, data.download_timeout, :no_line}

  ## NC download (WC → CEC)

  defp download_line(line, %{transfer: d} = data) do
    next = rem(d.count + 1, 10_000)
    last = if d.count > 0, do: rem(d.count, 10_000)

    case Reply.decode_line(line, bcc: data.bcc) do
      {:error, error} ->
        {:download, reject(data, error.reason), [download_timer(data)]}

      {:ok, {:line, ^next, text}} ->
        store_download_line(line, text, d, data)

      {:ok, {:line, ^last, _text}} ->
        # the WC did not take our answer for its line: the same line again, stored once
        data = %{reply(data, {:line_ack, last}) | counters: bump(data.counters, :lines_again)}
        {:download, data, [download_timer(data)]}

      {:ok, {:line, n, _text}} ->
        Logger.warning("DOWNLOAD_HP #{d.number}: line #{n} came when #{next} was due")
        data = reject(data, :line_out_of_order)
        {:command, end_transfer(data, d.number, {:error, "PROGRAM LINE OUT OF ORDER"}), []}
    end
  end

  defp store_download_line(line, text, d, data) do
    data = %{data | counters: bump(data.counters, :lines_in)}
    telemetry(data, :nc_line, %{bytes: byte_size(text)}, %{direction: :in})

    d = %{
      d
      | lines: [text | d.lines],
        count: d.count + 1,
        bytes: d.bytes + byte_size(text) + 1,
        crc: ProgramCRC.add_line(d.crc, text)
    }

    cond do
      d.bytes > data.max_program_bytes ->
        data = reject(data, :program_too_large)
        why = "NC PROGRAM LARGER THAN #{data.max_program_bytes} BYTES"
        {:command, end_transfer(data, d.number, {:error, why}), []}

      String.trim(text) == "%" and d.count > 1 ->
        close_download(line, d, data)

      true ->
        data = reply(%{data | transfer: d}, {:line_ack, rem(d.count, 10_000)})
        {:download, data, [download_timer(data)]}
    end
  end

  # The closing `%`: answered `A` + the number of lines + `/` + the CRC of what came, whatever
  # follows, so the WC can compare the whole program too (and a resend of the closing line
  # gets the same answer). The program is stored only if it is the one the WC named (when it
  # named one) and not larger than a program may be (PROTOCOLS.md §2 "Program size limit");
  # otherwise the command ends ERROR and the NC file and the library keep what they had.
  defp close_download(line, d, data) do
    lines = Enum.reverse(d.lines)
    answer = {:line_ack, rem(d.count, 10_000), d.crc}

    # d.bytes: the size of the program's text, every line with its LF
    refused =
      with :ok <- program_crc(d.expected, d.crc),
           do: Vws.Links.DNC.Program.check_size(d.bytes)

    case refused do
      :ok ->
        store_download(line, lines, answer, d, data)

      {:error, why} ->
        Logger.warning(
          "DOWNLOAD_HP #{d.number}: #{d.count} lines received, not stored: #{why}; " <>
            "the NC file is kept as it was"
        )

        telemetry(data, :string_rejected, %{bytes: 0}, %{reason: refusal(why)})
        data = reply(data, answer)
        data = end_transfer(data, d.number, {:error, why})
        {:command, %{data | last_closing: {line, answer}}, []}
    end
  end

  defp refusal("PROGRAM TOO LARGE" <> _), do: :program_too_large
  defp refusal(_why), do: :program_crc

  defp program_crc(nil, _crc), do: :ok
  defp program_crc({:error, why}, _crc), do: {:error, why}
  defp program_crc(crc, crc), do: :ok

  defp program_crc(expected, crc),
    do: {:error, "PROGRAM CRC #{ProgramCRC.format(crc)} EXPECTED #{ProgramCRC.format(expected)}"}

  defp store_download(line, lines, answer, d, data) do
    # into the program library first (issue 18), when the workstation has one
    case with(
           :ok <- Vws.CEC.Library.store_download(data.workstation, lines),
           do: Mailbox.put_nc_file(data.workstation, lines)
         ) do
      :ok ->
        data = reply(data, answer)
        Logger.info("DOWNLOAD_HP #{d.number}: #{d.count} lines stored as the NC file")
        data = end_transfer(data, d.number, :done)
        {:command, %{data | last_closing: {line, answer}}, []}

      {:error, reason} ->
        data = reject(data, :journal_unavailable)
        Logger.error("DOWNLOAD_HP #{d.number}: NC file not stored: #{inspect(reason)}")
        why = "NC FILE NOT STORED #{Vws.Codecs.WC.Words.of(reason)}"
        {:command, end_transfer(data, d.number, {:error, why}), []}
    end
  end

  ## NC upload (CEC → WC)

  defp send_upload_line(%{transfer: %{lines: [line | rest]} = u} = data) do
    telemetry(data, :nc_line, %{bytes: byte_size(line)}, %{direction: :out})
    data = reply(data, {:line, rem(u.sent + 1, 10_000), upload_text(line, rest, u)})

    {:upload, %{data | counters: bump(data.counters, :lines_out)},
     [{:state_timeout, data.upload_timeout, :no_answer}]}
  end

  defp upload_answer(line, %{transfer: u} = data) do
    this = rem(u.sent + 1, 10_000)
    previous = if u.sent > 0, do: rem(u.sent, 10_000)

    case Reply.decode(line, bcc: data.bcc) do
      {:ok, {:line_ack, ^this}} ->
        case u.lines do
          [_last] ->
            Logger.info("UPLOAD_SUN #{u.number}: #{u.sent + 1} lines sent")
            {:command, end_transfer(data, u.number, :done), []}

          [sent | rest] ->
            u = %{
              u
              | lines: rest,
                sent: u.sent + 1,
                retries: 0,
                bytes: u.bytes + byte_size(sent) + 1
            }

            send_upload_line(%{data | transfer: u})
        end

      {:ok, {:line_ack, ^previous}} ->
        # a late second answer to the line before (sent again after a silence): nothing new
        {:upload, data, []}

      {:ok, :nak} ->
        resend_upload_line(data)

      _ ->
        # a damaged answer, or one naming another line: this line is not known to be stored
        Logger.warning(
          "during UPLOAD_SUN the WC sent #{inspect(line)}; expected A#{Command.pad4(this)}"
        )

        resend_upload_line(data)
    end
  end

  # The closing `%` carries the program's CRC as `%/cccc` (PROTOCOLS.md §1 "Whole-program
  # check"): the `%` stays first, so a WC that looks only for `%` still ends there.
  defp upload_text(line, [], u) do
    if String.trim(line) == "%" and u.total > 1,
      do: ProgramCRC.closing_line(line, u.crc),
      else: line
  end

  defp upload_text(line, _rest, _u), do: line

  defp resend_upload_line(%{transfer: u} = data) do
    if u.retries >= data.upload_retries do
      why = "UPLOAD LINE #{u.sent + 1} NOT ACKNOWLEDGED AFTER #{u.retries + 1} TRIES"
      {:command, end_transfer(data, u.number, {:error, why}), []}
    else
      send_upload_line(%{data | transfer: %{u | retries: u.retries + 1}})
    end
  end

  ## Transfer endings

  defp abort_transfer(%{transfer: nil} = data, _why), do: data

  defp abort_transfer(%{transfer: %{kind: :download} = d} = data, why),
    do: end_transfer(data, d.number, {:error, "#{why} DURING DOWNLOAD AFTER #{d.count} LINES"})

  defp abort_transfer(%{transfer: %{kind: :upload} = u} = data, why),
    do: end_transfer(data, u.number, {:error, "#{why} DURING UPLOAD AFTER #{u.sent} LINES"})

  defp end_transfer(data, number, status) do
    Mailbox.finish(data.workstation, :monarch, number, status)

    Vws.Telemetry.execute([:vws, :partition, :command_finished], %{duration: 0}, %{
      workstation: data.workstation,
      partition: :monarch,
      command: number,
      status: status
    })

    %{data | transfer: nil}
  end

  ## Replies out

  defp reply(%{conn: nil} = data, _reply), do: data

  defp reply(data, reply) do
    iodata = Reply.encode(reply, bcc: data.bcc)
    bytes = IO.iodata_to_binary(iodata)

    case Transport.send(data.conn, bytes) do
      :ok ->
        telemetry(data, :reply_sent, %{bytes: byte_size(bytes)}, %{kind: reply_kind(reply)})
        record(data, :out, String.trim_trailing(bytes, "\r\n"))

      {:error, reason} ->
        # a WC that does not read (send_timeout) or is gone: drop it rather than wait on it
        peer = Transport.peer(data.conn)
        Transport.close(data.conn)
        lost = {:next_event, :internal, {:link_lost, peer, "reply not sent: #{inspect(reason)}"}}
        %{data | conn: nil, pending: [lost | data.pending]}
    end
  end

  defp reply_kind(reply) when is_atom(reply), do: reply
  defp reply_kind(reply) when is_tuple(reply), do: elem(reply, 0)

  defp record(data, direction, line) do
    entry = {now_ms(), direction, line}
    Events.cause(data.workstation, :wc_dialogue, entry)
    queue = :queue.in(entry, data.dialogue)

    if data.dialogue_size >= @dialogue_length do
      %{data | dialogue: :queue.drop(queue)}
    else
      %{data | dialogue: queue, dialogue_size: data.dialogue_size + 1}
    end
  end

  ## Helpers

  defp telemetry(data, event, measurements, metadata) do
    Vws.Telemetry.execute(
      [:vws, :sun_comm, event],
      measurements,
      Map.put(metadata, :workstation, data.workstation)
    )
  end

  defp bump(counters, key), do: Map.update!(counters, key, &(&1 + 1))
  defp now_ms, do: System.monotonic_time(:millisecond)

  # an NC transfer's progress for info/1: lines and bytes so far, the totals when known (an
  # upload's; a download's length is not announced), and its start (monotonic ms)
  defp transfer_info(:download, d),
    do: %{
      kind: "DOWNLOAD_HP",
      number: d.number,
      lines: d.count,
      bytes: d.bytes,
      total_lines: nil,
      total_bytes: nil,
      started_ms: d.started
    }

  defp transfer_info(:upload, u),
    do: %{
      kind: "UPLOAD_SUN",
      number: u.number,
      lines: u.sent,
      bytes: u.bytes,
      total_lines: u.total,
      total_bytes: u.total_bytes,
      started_ms: u.started
    }

  defp transfer_info(_state, _transfer), do: nil

  defp mode_name(:download, d), do: {:download, d.number, d.count}
  defp mode_name(:upload, u), do: {:upload, u.number, u.sent}
  defp mode_name(_state, _transfer), do: :command
end
