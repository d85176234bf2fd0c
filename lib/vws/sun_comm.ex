defmodule Vws.SunComm do
  @moduledoc """
  SUN_COMM (seed §2.3.1–2.3.7): owns the link to the workstation controller (WC), checks every
  string's BCC and answers `05A…` or `E` at once, applies the Parser's rules, hands each command to
  its partition (CMD_IN + CAUSE EVENT) and answers status commands from the mailboxes alone.

  ## The link

  One WC at a time, as on a serial line. On a tty it opens the device and reopens it if it goes
  away. On a TCP (or loopback) endpoint SUN_COMM listens, under this policy (decisions; issue 16):

    * **who may connect**: loopback only, unless `:allow` lists the addresses and networks that
      may (`Vws.Transport.Policy`); listening on an address that is not loopback without an
      allow-list is refused at start. Others are closed by the acceptor before SUN_COMM sees them.
    * **takeover**: a new connection replaces the current WC only when the current one has been
      silent (nothing received) for `:takeover_after` ms; otherwise the newcomer is closed. A WC
      that restarts after losing its link without a close (a half-open connection) gets in after
      that time. Every takeover and every refusal is logged with both peers.
    * **send timeout**: an answer the WC has not made room for within `:send_timeout` ms closes
      the connection (a WC that never reads is dropped; SUN_COMM is blocked at most that long).

  Nothing is read before the workstation has caused OK_TO_PROCEED.

  ## Rules (PROTOCOLS.md §1)

    1. a command-set letter appears at most once in a string;
    2. a string with an S command contains nothing else;
    3. a command for a set whose previous command is in flight is not run: `ERROR BUSY <previous>`;
    4. a string that repeats the last accepted sequence number with the same bytes is a
       retransmission: acknowledged again, nothing executed. With other bytes it is a new string
       from a WC that restarted and numbers from where it began again (decision, issue 15): it is
       handled as any new string. (A resend damaged so that its BCC still matches cannot be told
       from it; the BCC is the link's only check, as everywhere else on this link.)
    5. an intact string that breaks a rule is acknowledged, nothing in it runs, and each of its
       commands answers `ERROR <rule>` on its next status query. A command for a set letter the
       CEC does not know (`Q0005…`) breaks the rule `UNKNOWN COMMAND SET Q`: its error is
       queryable as status `Q_CMD` (`0005ERROR UNKNOWN COMMAND SET Q`), and every other command
       of that string answers the same error under its own status (decision, issue 15).

  ## Lines that are no string (decision, issue 15)

  An empty line and a line over `:max_line` bytes (1024) are answered `E` at once — the long one
  as soon as its 1025th byte arrives, not when its LF does; the rest of it, up to its LF, is
  discarded without a further answer. A line whose end never comes is dropped and answered `E`
  after `:partial_line_timeout`.

  ## NC line transfers (PROTOCOLS.md §1 "NC download", "NC upload")

  Program lines are numbered: `nnnn` + text + BCC, answered `A` + `nnnn` + BCC (stored) or `E`
  (damaged). After acknowledging a string carrying `M…DOWNLOAD_HP`, SUN_COMM reads lines 0001,
  0002, … until the closing `%` (a `%` as the very first line is the tape's leading rewind stop and
  is kept). A line carrying the number just stored is a resend after a damaged answer: answered
  again, not stored twice; any other number ends the command `ERROR PROGRAM LINE OUT OF ORDER`. The
  closing `%` is answered `A` + the number of lines stored, the program is journaled as the NC file
  and the Monarch command ends `DONE`; a resend of that closing line after the command ended is
  answered the same again. After acknowledging `M…UPLOAD_SUN` it sends NC_UP line by line; a line
  answered `E`, with a damaged answer, with another number or not at all is sent again (at most
  `:upload_retries` times); the command ends `DONE` when the WC has answered the closing `%` with
  its number (`ERROR NO UPLOADED PROGRAM` when NC_UP is empty). A status query during an upload is
  answered and the upload goes on (a WC that took the closing line asks its command's status
  while its answer reached us damaged: the closing line goes again, it answers again); any other
  string during a transfer means the WC left it. A transfer that stalls or loses the link ends
  the Monarch command `ERROR` with the reason.

  ## Options

    * `:workstation` (required), `:wc` — endpoint string or `nil` (no link)
    * `:bcc` — `:sum` (default) or `:xor`
    * `:max_line` — longest line accepted, default 1024 bytes
    * `:allow` — who may connect: `Vws.Transport.Policy` allow-list (`"10.0.0.5,10.0.0.0/24"`;
      default loopback only)
    * `:takeover_after` — ms of silence of the current WC after which a new connection may
      replace it (10 000)
    * `:takeover_grace` — ms a new connection refused by that rule waits for the current WC's
      connection to end before it is closed (500): a WC that closes one connection and opens
      the next at once (`bin/vws-wc`, `socat` per command) is let in, not refused for the close
      SUN_COMM had not yet seen
    * `:send_timeout` — ms an answer may wait for the WC to read before the link is dropped (5 000)
    * `:download_timeout` — ms without a program line before a download is abandoned (30 000)
    * `:upload_timeout` — ms to wait for the WC's `A`/`E` to an uploaded line (5 000)
    * `:upload_retries` — resends of one uploaded line before giving up (5)
    * `:max_program_bytes` — largest NC program accepted (4 MiB)
    * `:tty_retry` — ms between attempts to (re)open a tty (1 000)
    * `:partial_line_timeout` — ms of silence after the start of a line before the unfinished
      line is dropped and answered `E` (500; decision: a CR LF damaged on the line would
      otherwise leave a program-line transfer waiting)
  """
  use GenServer
  require Logger

  alias Vws.{Events, Mailbox, Transport}
  alias Vws.WC.{Command, CommandString, LineDecoder, Reply}

  @dialogue_length 200

  @doc false
  def child_spec(opts) do
    %{id: :sun_comm, start: {__MODULE__, :start_link, [opts]}, shutdown: 5_000}
  end

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    GenServer.start_link(__MODULE__, opts, name: Vws.Names.via(ws, :sun_comm))
  end

  @doc """
  SUN_COMM's state for inspection: endpoint, where it listens, the WC peer, the transfer mode and
  counters.
  """
  @spec info(term) :: map
  def info(ws), do: GenServer.call(Vws.Names.via(ws, :sun_comm), :info)

  @doc "The endpoint SUN_COMM listens on (with the real port when port 0 was asked), or nil."
  @spec listening(term) :: Vws.Endpoint.t() | nil
  def listening(ws), do: info(ws).listening

  @doc "The most recent lines of the WC dialogue, oldest first: `{monotonic_ms, :in | :out, line}`."
  @spec dialogue(term) :: [{integer, :in | :out, binary}]
  def dialogue(ws), do: GenServer.call(Vws.Names.via(ws, :sun_comm), :dialogue)

  ## Server

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    Logger.metadata(workstation: ws, partition: :sun_comm)

    case link_policy(opts) do
      {:ok, allow} -> init(opts, ws, allow)
      {:error, message} -> {:stop, {:wc_link_policy, message}}
    end
  end

  # The allow-list, and whether SUN_COMM may listen where it is told to under it.
  defp link_policy(opts) do
    with {:ok, allow} <- Vws.Transport.Policy.parse_allow(opts[:allow]),
         :ok <- check_listen(opts[:wc], allow) do
      {:ok, allow}
    else
      {:error, message} ->
        Logger.error("SUN_COMM cannot start: #{message}")
        {:error, message}
    end
  end

  defp check_listen(nil, _allow), do: :ok
  defp check_listen(wc, allow), do: Vws.Transport.Policy.check_listen(wc, allow)

  defp init(opts, ws, allow) do
    Process.flag(:trap_exit, true)
    Events.create(ws, :wc_dialogue)
    :ok = Events.subscribe(ws, :ok_to_proceed)

    state = %{
      workstation: ws,
      endpoint: opts[:wc],
      bcc: Keyword.get(opts, :bcc, :sum),
      max_line: Keyword.get(opts, :max_line, 1024),
      download_timeout: Keyword.get(opts, :download_timeout, 30_000),
      upload_timeout: Keyword.get(opts, :upload_timeout, 5_000),
      upload_retries: Keyword.get(opts, :upload_retries, 5),
      max_program_bytes: Keyword.get(opts, :max_program_bytes, 4 * 1024 * 1024),
      tty_retry: Keyword.get(opts, :tty_retry, 1_000),
      partial_line_timeout: Keyword.get(opts, :partial_line_timeout, 500),
      allow: allow,
      takeover_after: Keyword.get(opts, :takeover_after, 10_000),
      takeover_grace: Keyword.get(opts, :takeover_grace, 500),
      waiting: nil,
      send_timeout: Keyword.get(opts, :send_timeout, 5_000),
      last_heard: nil,
      partial: nil,
      ok_to_proceed: false,
      listener: nil,
      listening: nil,
      acceptor: nil,
      conn: nil,
      decoder: nil,
      mode: :command,
      # the closing line of the last download and its answer: a resend of it after the
      # transfer ended (its answer was damaged) is answered again
      last_closing: nil,
      timer: nil,
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
    }

    if (Events.count(ws, :ok_to_proceed) || 0) > 0 do
      {:ok, %{state | ok_to_proceed: true}, {:continue, :open}}
    else
      {:ok, state}
    end
  end

  @impl true
  def handle_continue(:open, %{endpoint: nil} = s), do: {:noreply, s}

  def handle_continue(:open, s) do
    endpoint = Vws.Endpoint.parse!(s.endpoint)

    if endpoint.kind == :tty do
      {:noreply, open_tty(s)}
    else
      case Transport.listen(endpoint, send_timeout: s.send_timeout) do
        {:ok, listener} ->
          acceptor = Transport.start_acceptor(listener, self(), :wc_accepted, allow: s.allow)
          bound = Transport.listener_endpoint(listener)

          Logger.info(
            "SUN_COMM listening for the WC on #{bound} (#{Vws.Transport.Policy.describe(s.allow)})"
          )

          {:noreply, %{s | listener: listener, listening: bound, acceptor: acceptor}}

        {:error, reason} ->
          {:stop, {:cannot_listen, s.endpoint, reason}, s}
      end
    end
  end

  defp open_tty(s) do
    case Transport.connect(s.endpoint) do
      {:ok, conn} ->
        Vws.LogLimit.clear(:wc_tty, "WC tty #{s.endpoint} open")
        s = take_link(s, conn)
        %{s | listening: conn.endpoint}

      {:error, reason} ->
        # once, not at every try (once a second)
        Vws.LogLimit.warning(
          :wc_tty,
          "cannot open the WC tty #{s.endpoint}: #{inspect(reason)}; retrying",
          :error
        )

        Process.send_after(self(), :reopen_tty, s.tty_retry)
        s
    end
  end

  @impl true
  def handle_info({:vws_event, ws, :ok_to_proceed, _}, %{workstation: ws} = s) do
    if s.ok_to_proceed,
      do: {:noreply, s},
      else: {:noreply, %{s | ok_to_proceed: true}, {:continue, :open}}
  end

  def handle_info({:wc_accepted, conn}, s) do
    cond do
      s.conn == nil or silent_ms(s) >= s.takeover_after ->
        {:noreply, take_link(s, conn)}

      s.waiting != nil ->
        # one newcomer waits at a time; a second one is refused at once
        {:noreply, refuse(s, conn)}

      true ->
        # the current connection may have ended already, its close still on its way to us:
        # the newcomer waits (unread) a moment for it, and is refused only if it does not come
        ref = make_ref()
        Process.send_after(self(), {:takeover_grace, ref}, s.takeover_grace)
        {:noreply, %{s | waiting: {conn, ref}}}
    end
  end

  def handle_info({:takeover_grace, ref}, %{waiting: {conn, ref}} = s),
    do: {:noreply, refuse(%{s | waiting: nil}, conn)}

  def handle_info({:takeover_grace, _stale}, s), do: {:noreply, s}

  def handle_info(:reopen_tty, s), do: {:noreply, open_tty(s)}

  def handle_info({:transfer_timeout, ref}, %{timer: {ref, _}} = s),
    do: {:noreply, transfer_timeout(s)}

  def handle_info({:transfer_timeout, _stale}, s), do: {:noreply, s}

  def handle_info({:EXIT, pid, reason}, %{acceptor: pid} = s) do
    {:stop, {:acceptor_down, reason}, s}
  end

  def handle_info({:EXIT, _pid, _reason}, s), do: {:noreply, s}

  def handle_info({:partial_line, ref}, %{partial: {ref, _tref}} = s) do
    # the end of a line never came: its CR LF was lost or damaged on the line
    s = %{s | partial: nil, decoder: s.decoder && LineDecoder.new(max_line: s.max_line)}
    s = record(s, :in, "<unfinished line dropped after #{s.partial_line_timeout} ms>")

    s =
      case s.mode do
        {:upload, _} -> s
        _ -> reject(s, :unfinished_line)
      end

    {:noreply, s}
  end

  def handle_info({:partial_line, _stale}, s), do: {:noreply, s}

  def handle_info(msg, %{conn: conn} = s) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        {lines, decoder} = LineDecoder.feed(s.decoder, bytes)
        s = %{s | last_heard: System.monotonic_time(:millisecond)}
        s = Enum.reduce(lines, %{s | decoder: decoder}, &handle_line/2)
        if s.conn, do: Transport.activate(s.conn)
        {:noreply, watch_partial_line(s)}

      :closed ->
        {:noreply, link_lost(s, "closed")}

      {:error, reason} ->
        {:noreply, link_lost(s, inspect(reason))}

      :unknown ->
        Logger.debug("SUN_COMM ignored #{inspect(msg, limit: 10)}")
        {:noreply, s}
    end
  end

  def handle_info(msg, s) do
    Logger.debug("SUN_COMM ignored #{inspect(msg, limit: 10)}")
    {:noreply, s}
  end

  @impl true
  def handle_call(:info, _from, s) do
    {:reply,
     %{
       workstation: s.workstation,
       endpoint: s.endpoint,
       listening: s.listening,
       ok_to_proceed: s.ok_to_proceed,
       peer: s.conn && Transport.peer(s.conn),
       mode: mode_name(s.mode),
       transfer: transfer(s.mode),
       counters: s.counters
     }, s}
  end

  def handle_call(:dialogue, _from, s), do: {:reply, :queue.to_list(s.dialogue), s}

  @impl true
  def terminate(_reason, s) do
    if s.conn, do: Transport.close(s.conn)
    if s.waiting, do: Transport.close(elem(s.waiting, 0))
    if s.listener, do: Transport.close_listener(s.listener)
    :ok
  end

  ## The link

  defp take_link(s, conn) do
    s =
      if s.conn do
        Logger.warning(
          "WC connection from #{Transport.peer(conn)} takes over from #{Transport.peer(s.conn)}, which is closed"
        )

        old = s.conn
        s = abort_transfer(s, "WC LINK TAKEN OVER")
        Transport.close(old)

        telemetry(s, :wc_disconnected, %{count: 1}, %{
          peer: Transport.peer(old),
          reason: :taken_over
        })

        s
      else
        s
      end

    Logger.info("WC connected: #{Transport.peer(conn)}")
    telemetry(s, :wc_connected, %{count: 1}, %{peer: Transport.peer(conn)})
    Transport.activate(conn)

    %{
      s
      | conn: conn,
        last_heard: System.monotonic_time(:millisecond),
        decoder: LineDecoder.new(max_line: s.max_line),
        mode: :command,
        counters: bump(s.counters, :connections)
    }
  end

  defp silent_ms(s), do: System.monotonic_time(:millisecond) - s.last_heard

  defp refuse(s, conn) do
    Logger.warning(
      "WC connection from #{Transport.peer(conn)} refused: the WC on #{Transport.peer(s.conn)} " <>
        "was heard #{silent_ms(s)} ms ago (a takeover needs #{s.takeover_after} ms of silence)"
    )

    telemetry(s, :wc_refused, %{count: 1}, %{
      peer: Transport.peer(conn),
      current: Transport.peer(s.conn)
    })

    Transport.close(conn)
    s
  end

  # The current WC is gone: a newcomer waiting for that takes the link now.
  defp admit_waiting(%{waiting: {conn, _ref}} = s), do: take_link(%{s | waiting: nil}, conn)
  defp admit_waiting(s), do: s

  defp link_lost(s, why) do
    Logger.warning("WC link lost (#{why})")
    telemetry(s, :wc_disconnected, %{count: 1}, %{peer: Transport.peer(s.conn), reason: why})
    s = abort_transfer(s, "WC LINK LOST")
    s = %{s | conn: nil, decoder: nil}

    if s.listener == nil and s.endpoint do
      # a tty: open it again
      Process.send_after(self(), :reopen_tty, s.tty_retry)
    end

    admit_waiting(s)
  end

  ## Lines in

  # Bytes of an unfinished line start (or restart) the inter-character timer; a line whose end
  # does not follow within `partial_line_timeout` is dropped and answered `E` (a WC waiting on
  # the answer to a program line would otherwise wait for ever, and may not send it again
  # unasked: a line whose `A` was lost would be stored twice).
  defp watch_partial_line(%{partial: partial, decoder: decoder} = s) do
    if partial, do: Process.cancel_timer(elem(partial, 1))

    if decoder != nil and LineDecoder.buffered(decoder) > 0 do
      ref = make_ref()
      tref = Process.send_after(self(), {:partial_line, ref}, s.partial_line_timeout)
      %{s | partial: {ref, tref}}
    else
      %{s | partial: nil}
    end
  end

  defp handle_line({:error, error}, s) do
    record(s, :in, "<#{Exception.message(error)}>")
    |> reject(error.reason)
  end

  defp handle_line(line, s) do
    s = record(s, :in, line)

    case {s.mode, string_during_transfer(line, s)} do
      {:command, _} -> command_line(line, s)
      {_transfer, {:ok, cs}} -> command_string_in_transfer(cs, line, s)
      {{:download, _}, _} -> download_line(line, s)
      {{:upload, _}, _} -> upload_answer(line, s)
    end
  end

  # An intact command string during a program transfer: the WC is not in the transfer.
  defp string_during_transfer("*" <> _ = line, %{mode: {_, _}} = s),
    do: CommandString.decode(line, bcc: s.bcc)

  defp string_during_transfer(_line, _s), do: :no

  # The string that began the transfer, again: its acknowledgement was lost and the WC is
  # still waiting for it, so it is acknowledged again and the transfer begins afresh from its
  # first line (the WC sends or takes the program only after the acknowledgement). A status
  # query during an upload is answered and the upload goes on: it runs nothing, and a WC that
  # has taken the closing line asks its command's status while its answer reached us damaged —
  # the closing line goes again and it answers again. Any other string (and a status query
  # during a download, where the WC is the sender): the WC gave the transfer up; it ends
  # ERROR and the string is handled as usual.
  defp command_string_in_transfer(cs, line, %{mode: {kind, t}} = s) do
    cond do
      Mailbox.last_string(s.workstation) == {cs.sequence, line} ->
        restart_transfer(cs, kind, t, s)

      kind == :upload and status_string?(cs) ->
        accept_string(cs, line, s)

      true ->
        Logger.warning("string #{cs.sequence} during #{kind}: the WC left the transfer")
        command_line(line, abort_transfer(s, "COMMAND STRING FROM THE WC"))
    end
  end

  defp restart_transfer(cs, kind, t, s) do
    Logger.info(
      "string #{cs.sequence} again during #{kind}: acknowledged again, transfer restarted"
    )

    telemetry(s, :retransmission, %{count: 1}, %{sequence: cs.sequence})
    s = reply(%{s | counters: bump(s.counters, :retransmissions)}, {:ack, cs.sequence})

    case kind do
      :download -> start_download(s, t.number)
      :upload -> start_upload(s, t.number)
    end
  end

  defp reject(s, reason) do
    telemetry(s, :string_rejected, %{bytes: 0}, %{reason: reason})
    %{reply(s, :nak) | counters: bump(s.counters, :naks)}
  end

  defp command_line("", s), do: reject(s, :empty_line)

  defp command_line(line, %{last_closing: {line, answer}} = s) do
    Logger.info("the closing line of the last download again: answered again")
    %{reply(s, answer) | counters: bump(s.counters, :lines_again)}
  end

  defp command_line(line, s) do
    s = %{s | last_closing: nil}

    case CommandString.decode(line, bcc: s.bcc) do
      {:error, error} ->
        reject(s, error.reason)

      {:ok, cs} ->
        s = %{s | counters: bump(s.counters, :strings)}

        telemetry(s, :string_received, %{bytes: byte_size(line)}, %{
          sequence: cs.sequence,
          commands: length(cs.commands)
        })

        accept_string(cs, line, s)
    end
  end

  defp accept_string(cs, line, s) do
    ws = s.workstation

    cond do
      status_string?(cs) ->
        # status strings are not remembered for rule 4: answering one twice is harmless, and a
        # status poll between a lost acknowledgement and its resend must not hide the resend
        [status] = cs.commands
        text = Vws.Status.answer(ws, status.text)
        s = %{s | counters: bump(s.counters, :status_answers)}
        reply(s, {:status, status.number, text})

      Mailbox.last_string(ws) == {cs.sequence, line} ->
        Logger.info(
          "string #{cs.sequence} is a retransmission: acknowledged again, nothing executed"
        )

        telemetry(s, :retransmission, %{count: 1}, %{sequence: cs.sequence})
        s = %{s | counters: bump(s.counters, :retransmissions)}
        reply(s, {:ack, cs.sequence})

      journal_string(ws, cs, line) != :ok ->
        # not durable, so not acknowledged: the WC sends it again
        reject(s, :journal_unavailable)

      broken = broken_rule(cs) ->
        Mailbox.put_last_string(ws, cs.sequence, line)
        s = reply(s, {:ack, cs.sequence})
        Logger.warning("string #{cs.sequence} breaks a rule (#{broken}): nothing in it runs")
        telemetry(s, :rule_broken, %{count: 1}, %{sequence: cs.sequence, rule: broken})

        for %{set: set, number: n} <- cs.commands do
          case set do
            {:unknown, letter} -> Mailbox.put_unknown_status(ws, letter, n, {:error, broken})
            :ack -> :ok
            set -> Mailbox.put_status(ws, set, n, {:error, broken})
          end
        end

        %{s | counters: bump(s.counters, :rules_broken)}

      true ->
        Mailbox.put_last_string(ws, cs.sequence, line)
        s = reply(s, {:ack, cs.sequence})
        Enum.reduce(cs.commands, s, &dispatch/2)
    end
  end

  defp journal_string(ws, cs, line) do
    commands =
      for %{set: set, number: n} <- cs.commands, set in Mailbox.partitions(), do: {set, n}

    Vws.Journal.record(Mailbox.table(ws), {:string, cs.sequence, line, commands})
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

  defp dispatch(%{set: :ack} = command, s) do
    Logger.debug("acknowledgement command #{command.number} #{command.text}")
    s
  end

  defp dispatch(%{set: set, number: number, text: text}, s) do
    ws = s.workstation

    case Mailbox.dispatch(ws, set, number, text) do
      {:busy, previous} ->
        Logger.warning("#{set} command #{number} refused: command #{previous} still in flight")
        Mailbox.put_status(ws, set, number, {:error, "BUSY #{Command.pad4(previous)}"})
        s

      :ok ->
        telemetry(
          s,
          :command_dispatched,
          %{count: 1},
          %{partition: set, command: number, text: text},
          :partition
        )

        case set == :monarch && Vws.Commands.parse(:monarch, text) do
          {:ok, :download_hp} -> start_download(s, number)
          {:ok, :upload_sun} -> start_upload(s, number)
          _ -> cause(s, set, number)
        end
    end
  end

  defp cause(s, set, number) do
    :ok = Events.cause(s.workstation, set, number)
    s
  end

  ## NC download (WC → CEC)

  defp start_download(s, number) do
    Logger.info("DOWNLOAD_HP #{number}: reading program lines from the WC")

    arm(
      %{
        s
        | mode: {:download, %{number: number, lines: [], count: 0, bytes: 0, started: now_ms()}}
      },
      s.download_timeout
    )
  end

  defp download_line(line, %{mode: {:download, d}} = s) do
    next = rem(d.count + 1, 10_000)
    last = if d.count > 0, do: rem(d.count, 10_000)

    case Reply.decode_line(line, bcc: s.bcc) do
      {:error, error} ->
        s |> reject(error.reason) |> arm(s.download_timeout)

      {:ok, {:line, ^next, text}} ->
        store_download_line(line, text, d, s)

      {:ok, {:line, ^last, _text}} ->
        # the WC did not take our answer for its line: the same line again, stored once
        s = %{reply(s, {:line_ack, last}) | counters: bump(s.counters, :lines_again)}
        arm(s, s.download_timeout)

      {:ok, {:line, n, _text}} ->
        Logger.warning("DOWNLOAD_HP #{d.number}: line #{n} came when #{next} was due")

        end_transfer(
          reject(s, :line_out_of_order),
          d.number,
          {:error, "PROGRAM LINE OUT OF ORDER"}
        )
    end
  end

  defp store_download_line(line, text, d, s) do
    s = %{s | counters: bump(s.counters, :lines_in)}
    telemetry(s, :nc_line, %{bytes: byte_size(text)}, %{direction: :in})

    d = %{
      d
      | lines: [text | d.lines],
        count: d.count + 1,
        bytes: d.bytes + byte_size(text) + 1
    }

    cond do
      d.bytes > s.max_program_bytes ->
        s = reject(s, :program_too_large)
        end_transfer(s, d.number, {:error, "NC PROGRAM LARGER THAN #{s.max_program_bytes} BYTES"})

      String.trim(text) == "%" and d.count > 1 ->
        lines = Enum.reverse(d.lines)

        case Mailbox.put_nc_file(s.workstation, lines) do
          :ok ->
            # the closing line's answer: the number of lines stored, so both ends agree
            answer = {:line_ack, rem(d.count, 10_000)}
            s = reply(s, answer)
            Logger.info("DOWNLOAD_HP #{d.number}: #{d.count} lines stored as the NC file")
            %{end_transfer(s, d.number, :done) | last_closing: {line, answer}}

          {:error, reason} ->
            s = reject(s, :journal_unavailable)
            end_transfer(s, d.number, {:error, "NC FILE NOT STORED #{inspect(reason)}"})
        end

      true ->
        s = reply(s, {:line_ack, rem(d.count, 10_000)})
        arm(%{s | mode: {:download, d}}, s.download_timeout)
    end
  end

  ## NC upload (CEC → WC)

  defp start_upload(s, number) do
    case Mailbox.nc_up(s.workstation) do
      [] ->
        Mailbox.finish(s.workstation, :monarch, number, {:error, "NO UPLOADED PROGRAM"})
        s

      lines ->
        Logger.info("UPLOAD_SUN #{number}: sending #{length(lines)} lines to the WC")

        send_upload_line(%{
          s
          | mode:
              {:upload,
               %{
                 number: number,
                 lines: lines,
                 sent: 0,
                 retries: 0,
                 started: now_ms(),
                 total: length(lines),
                 bytes: 0,
                 total_bytes: Enum.reduce(lines, 0, &(byte_size(&1) + 1 + &2))
               }}
        })
    end
  end

  defp send_upload_line(%{mode: {:upload, %{lines: [line | _]} = u}} = s) do
    telemetry(s, :nc_line, %{bytes: byte_size(line)}, %{direction: :out})
    s = reply(s, {:line, rem(u.sent + 1, 10_000), line})
    arm(%{s | counters: bump(s.counters, :lines_out)}, s.upload_timeout)
  end

  defp upload_answer(line, %{mode: {:upload, u}} = s) do
    this = rem(u.sent + 1, 10_000)
    previous = if u.sent > 0, do: rem(u.sent, 10_000)

    case Reply.decode(line, bcc: s.bcc) do
      {:ok, {:line_ack, ^this}} ->
        case u.lines do
          [_last] ->
            Logger.info("UPLOAD_SUN #{u.number}: #{u.sent + 1} lines sent")
            end_transfer(s, u.number, :done)

          [_ | rest] ->
            send_upload_line(%{
              s
              | mode:
                  {:upload,
                   %{
                     u
                     | lines: rest,
                       sent: u.sent + 1,
                       retries: 0,
                       bytes: u.bytes + byte_size(hd(u.lines)) + 1
                   }}
            })
        end

      {:ok, {:line_ack, ^previous}} ->
        # a late second answer to the line before (sent again after a silence): nothing new
        s

      {:ok, :nak} ->
        resend_upload_line(s, u)

      _ ->
        # a damaged answer, or one naming another line: this line is not known to be stored
        Logger.warning(
          "during UPLOAD_SUN the WC sent #{inspect(line)}; expected A#{Command.pad4(this)}"
        )

        resend_upload_line(s, u)
    end
  end

  defp resend_upload_line(s, u) do
    if u.retries >= s.upload_retries do
      end_transfer(
        s,
        u.number,
        {:error, "UPLOAD LINE #{u.sent + 1} NOT ACKNOWLEDGED AFTER #{u.retries + 1} TRIES"}
      )
    else
      send_upload_line(%{s | mode: {:upload, %{u | retries: u.retries + 1}}})
    end
  end

  ## Transfer timers and endings

  defp arm(s, ms) do
    s = disarm(s)
    ref = make_ref()
    {ref, Process.send_after(self(), {:transfer_timeout, ref}, ms)} |> then(&%{s | timer: &1})
  end

  defp disarm(%{timer: nil} = s), do: s

  defp disarm(%{timer: {_ref, tref}} = s) do
    Process.cancel_timer(tref)
    %{s | timer: nil}
  end

  defp transfer_timeout(%{mode: {:download, d}} = s) do
    end_transfer(s, d.number, {:error, "DOWNLOAD STALLED AFTER #{d.count} LINES"})
  end

  defp transfer_timeout(%{mode: {:upload, u}} = s), do: resend_upload_line(s, u)
  defp transfer_timeout(s), do: disarm(s)

  defp abort_transfer(%{mode: {:download, d}} = s, why),
    do: end_transfer(s, d.number, {:error, "#{why} DURING DOWNLOAD AFTER #{d.count} LINES"})

  defp abort_transfer(%{mode: {:upload, u}} = s, why),
    do: end_transfer(s, u.number, {:error, "#{why} DURING UPLOAD AFTER #{u.sent} LINES"})

  defp abort_transfer(s, _why), do: s

  defp end_transfer(s, number, status) do
    Mailbox.finish(s.workstation, :monarch, number, status)

    Vws.Telemetry.execute([:vws, :partition, :command_finished], %{duration: 0}, %{
      workstation: s.workstation,
      partition: :monarch,
      command: number,
      status: status
    })

    %{disarm(s) | mode: :command}
  end

  ## Replies out

  defp reply(%{conn: nil} = s, _reply), do: s

  defp reply(s, reply) do
    iodata = Reply.encode(reply, bcc: s.bcc)
    bytes = IO.iodata_to_binary(iodata)

    case Transport.send(s.conn, bytes) do
      :ok ->
        telemetry(s, :reply_sent, %{bytes: byte_size(bytes)}, %{kind: reply_kind(reply)})
        record(s, :out, String.trim_trailing(bytes, "\r\n"))

      {:error, reason} ->
        # a WC that does not read (send_timeout) or is gone: drop it rather than wait on it
        Transport.close(s.conn)
        link_lost(s, "reply not sent: #{inspect(reason)}")
    end
  end

  defp reply_kind(reply) when is_atom(reply), do: reply
  defp reply_kind(reply) when is_tuple(reply), do: elem(reply, 0)

  defp record(s, direction, line) do
    entry = {System.monotonic_time(:millisecond), direction, line}
    Events.cause(s.workstation, :wc_dialogue, entry)
    queue = :queue.in(entry, s.dialogue)

    if s.dialogue_size >= @dialogue_length do
      %{s | dialogue: :queue.drop(queue)}
    else
      %{s | dialogue: queue, dialogue_size: s.dialogue_size + 1}
    end
  end

  ## Helpers

  defp telemetry(s, event, measurements, metadata, component \\ :sun_comm) do
    Vws.Telemetry.execute(
      [:vws, component, event],
      measurements,
      Map.put(metadata, :workstation, s.workstation)
    )
  end

  defp bump(counters, key), do: Map.update!(counters, key, &(&1 + 1))

  # an NC transfer's progress for info/1: lines and bytes so far, the totals when known (an
  # upload's; a download's length is not announced), and its start (monotonic ms)
  defp transfer(:command), do: nil

  defp transfer({:download, d}),
    do: %{
      kind: "DOWNLOAD_HP",
      number: d.number,
      lines: d.count,
      bytes: d.bytes,
      total_lines: nil,
      total_bytes: nil,
      started_ms: d.started
    }

  defp transfer({:upload, u}),
    do: %{
      kind: "UPLOAD_SUN",
      number: u.number,
      lines: u.sent,
      bytes: u.bytes,
      total_lines: u.total,
      total_bytes: u.total_bytes,
      started_ms: u.started
    }

  defp now_ms, do: System.monotonic_time(:millisecond)

  defp mode_name(:command), do: :command
  defp mode_name({:download, d}), do: {:download, d.number, d.count}
  defp mode_name({:upload, u}), do: {:upload, u.number, u.sent}
end
