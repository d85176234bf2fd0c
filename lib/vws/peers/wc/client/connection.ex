defmodule Vws.Peers.WC.Client.Connection do
  @moduledoc false
  # The state machine behind `Vws.Peers.WC.Client`. States:
  #
  #   :idle           nothing on the link; a request starts here
  #   :awaiting_reply a string (commands or a status query) is out; waiting for 05A / NN S / E
  #   :downloading    DOWNLOAD_HP(cccc) acknowledged; sending numbered program lines, each
  #                   answered Annnn+BCC (stored) — the closing % Annnn/cccc+BCC, the CRC of
  #                   what the CEC stored — anything else, or nothing, sends the same line again
  #   :uploading      UPLOAD_SUN acknowledged; receiving numbered program lines, answering
  #                   Annnn+BCC or E; a resend of the line just stored is answered again; the
  #                   closing line %/cccc carries the program's CRC, compared with ours
  #   :disconnected   the link closed; the next request opens it again
  #
  # Requests arriving while a request is under way are postponed, so one exchange is on the link
  # at a time. The reply timer is a state_timeout: a stray line does not reset it.

  @behaviour :gen_statem
  require Logger

  alias Vws.Links.Transport
  alias Vws.Peers.WC.ClientError
  alias Vws.Codecs.WC.{Command, CommandString, LineDecoder, ProgramCRC, Reply}
  alias Vws.Peers.WC.Client.Event

  import Vws.Codecs.WC.Command, only: [pad4: 1]

  @log_length 1_000
  @max_line 4_096

  @impl true
  def callback_mode, do: [:state_functions, :state_enter]

  @impl true
  def init({conn, endpoint, opts}) do
    data = %{
      conn: conn,
      endpoint: endpoint,
      bcc: Keyword.get(opts, :bcc, :sum),
      decoder: LineDecoder.new(max_line: @max_line),
      next_seq: option(opts, :sequence, 1, 0..9999),
      next: Map.new(Keyword.get(opts, :numbers, %{})),
      max_resends: option(opts, :max_resends, 3, 0..100),
      reply_timeout: Keyword.get(opts, :reply_timeout, 5_000),
      line_timeout: Keyword.get(opts, :line_timeout, 5_000),
      req: nil,
      # the closing line of the last upload and our answer, bytes: the CEC sends it again
      # when our answer reached it damaged, after we were done
      last_closing: nil,
      counters: %{
        strings: 0,
        commands: 0,
        status_queries: 0,
        resends: 0,
        naks: 0,
        timeouts: 0,
        lines_sent: 0,
        lines_received: 0,
        naks_sent: 0,
        stray: 0,
        lines_again: 0,
        reconnects: 0,
        transfers_broken: 0
      },
      subscribers: %{},
      log: :queue.new(),
      log_size: 0,
      t0: System.monotonic_time(:millisecond)
    }

    data = if pid = opts[:subscribe], do: add_subscriber(data, pid), else: data
    {:ok, :idle, data}
  end

  defp option(opts, key, default, range) do
    case Keyword.get(opts, key, default) do
      n when is_integer(n) -> if n in range, do: n, else: raise(ArgumentError, "#{key}: #{n}")
      other -> raise ArgumentError, "#{key} must be an integer, got #{inspect(other)}"
    end
  end

  @impl true
  def terminate(_reason, _state, %{conn: conn}) do
    if conn, do: Transport.close(conn)
    :ok
  end

  ## States

  @doc false
  def idle(:enter, _old, _data), do: :keep_state_and_data

  # the closing line of an upload is answered again until something else than a status query
  # is asked: the CEC may send it again while the WC polls the command's status
  def idle({:call, from}, {:request, {:status, _} = request}, data),
    do: start(request, from, data)

  def idle({:call, from}, {:request, request}, data),
    do: start(request, from, %{data | last_closing: nil})

  def idle(type, content, data), do: common(type, content, data)

  @doc false
  def awaiting_reply(:enter, _old, data),
    do: {:keep_state_and_data, [{:state_timeout, data.reply_timeout, :no_reply}]}

  def awaiting_reply({:call, _}, {:request, _}, _data), do: {:keep_state_and_data, :postpone}

  def awaiting_reply(:internal, {:line, line}, %{last_closing: {line, _}} = data),
    do: common(:internal, {:line, line}, data)

  def awaiting_reply(:internal, {:line, line}, data),
    do: reply_line(Reply.decode(line, bcc: data.bcc), line, data)

  def awaiting_reply(:internal, {:line_error, error}, data) do
    data = emit(data, :received, :damaged, nil, "damaged reply: #{Exception.message(error)}")
    resend(data, :damaged)
  end

  def awaiting_reply(:state_timeout, :no_reply, data) do
    data = bump(data, :timeouts)

    data =
      emit(
        data,
        :note,
        :note,
        nil,
        "no reply to string #{pad4(data.req.seq)} within #{data.reply_timeout} ms"
      )

    resend(data, :timeout)
  end

  def awaiting_reply(type, content, data), do: common(type, content, data)

  @doc false
  def downloading(:enter, _old, data), do: send_program_line(data)
  def downloading({:call, _}, {:request, _}, _data), do: {:keep_state_and_data, :postpone}

  def downloading(:internal, {:line, line}, %{req: req} = data) do
    n = line_number(req.sent + 1)
    closing? = tl(req.lines) == []

    case Reply.decode(line, bcc: data.bcc) do
      {:ok, {:line_ack, ^n}} when not closing? ->
        data = emit(data, :received, :line_ack, line, "A#{pad4(n)}: program line #{n} stored")
        rest = tl(req.lines)
        send_program_line(%{data | req: %{req | lines: rest, sent: req.sent + 1, tries: 1}})

      {:ok, {:line_ack, ^n, crc}} when closing? ->
        # the CEC's count and CRC of the whole program it took (PROTOCOLS.md §1
        # "Whole-program check"); with the CRC named in the command, it stores only a program
        # whose CRC is the one named
        stored = "A#{pad4(n)}/#{ProgramCRC.format(crc)}: #{n} lines"

        if crc == req.crc do
          data = emit(data, :received, :line_ack, line, "#{stored}, the program's CRC: stored")
          :gen_statem.reply(req.from, {:ok, {"M", req.number}})
          {:next_state, :idle, %{data | req: nil}}
        else
          data = emit(data, :received, :line_ack, line, "#{stored}, not the program's CRC")
          program_crc_failed(data, :download, req.crc, crc)
        end

      {:ok, :nak} ->
        data = emit(bump(data, :naks), :received, :nak, line, "E: program line #{n} damaged")
        resend_program_line(data, "answered E")

      {:ok, _other} ->
        # an answer naming another line, or no line answer at all: not known to be stored
        resend_program_line(stray(data, line), "answered #{inspect(line)}")

      {:error, error} ->
        data =
          emit(data, :received, :damaged, line, "damaged answer: #{Exception.message(error)}")

        resend_program_line(data, "its answer arrived damaged")
    end
  end

  def downloading(:internal, {:line_error, error}, data) do
    data = emit(data, :received, :damaged, nil, "damaged answer: #{Exception.message(error)}")
    resend_program_line(data, "its answer arrived damaged")
  end

  def downloading(:state_timeout, :no_answer, data) do
    # The line carries its number: if it was stored and only the answer was lost, the CEC
    # answers the resend again and does not store it twice.
    data = bump(data, :timeouts)
    resend_program_line(data, "no answer within #{data.line_timeout} ms")
  end

  def downloading(type, content, data), do: common(type, content, data)

  @doc false
  def uploading(:enter, _old, data),
    do: {:keep_state_and_data, [{:state_timeout, data.line_timeout, :no_line}]}

  def uploading({:call, _}, {:request, _}, _data), do: {:keep_state_and_data, :postpone}

  def uploading(:internal, {:line, line}, %{req: req} = data) do
    count = length(req.received)
    n = line_number(count + 1)
    last = if count > 0, do: line_number(count)

    case Reply.decode_line(line, bcc: data.bcc) do
      {:ok, {:line, ^n, text}} ->
        data =
          emit(bump(data, :lines_received), :received, :program_line, line, "program line #{n}")

        answer = answer_line(data, n, "A#{pad4(n)}: line #{n} stored")
        data = answer.data

        case closing_line(text, count + 1) do
          {:closing, stored, crc} ->
            lines = Enum.reverse([stored | req.received])
            data = %{data | last_closing: {line, answer.bytes}}
            upload_closed(data, lines, crc)

          :not_closing ->
            {:keep_state, %{data | req: %{req | received: [text | req.received]}},
             [{:state_timeout, data.line_timeout, :no_line}]}
        end

      {:ok, {:line, ^last, _text}} ->
        data = emit(data, :received, :program_line, line, "program line #{last} again")
        data = answer_line(bump(data, :lines_again), last, "A#{pad4(last)}: stored already").data
        {:keep_state, data, [{:state_timeout, data.line_timeout, :no_line}]}

      {:ok, {:line, other, _text}} ->
        data = emit(data, :received, :program_line, line, "program line #{other}")
        transfer_failed(data, :upload, count + 1, "line #{other} came when #{n} was due")

      {:error, error} ->
        damaged_upload_line(data, line, error)
    end
  end

  def uploading(:internal, {:line_error, error}, data),
    do: damaged_upload_line(data, nil, error)

  def uploading(:state_timeout, :no_line, %{req: %{received: []} = req} = data) do
    :gen_statem.reply(req.from, {:no_lines, req.number, data.reply_timeout})
    {:next_state, :idle, %{data | req: nil}}
  end

  def uploading(:state_timeout, :no_line, data) do
    n = length(data.req.received) + 1
    transfer_failed(data, :upload, n, "no line within #{data.line_timeout} ms")
  end

  def uploading(type, content, data), do: common(type, content, data)

  @doc false
  def disconnected(:enter, _old, _data), do: :keep_state_and_data

  def disconnected({:call, from}, {:request, _}, data) do
    case reopen(data) do
      {:ok, data} ->
        {:next_state, :idle, data, [:postpone]}

      {:error, data} ->
        {:keep_state, data, [{:reply, from, {:error, %ClientError{reason: :closed}}}]}
    end
  end

  def disconnected(type, content, data), do: common(type, content, data)

  ## Requests

  defp start({:commands, commands}, from, data),
    do: start_string(commands, %{from: from, kind: :commands, then: nil}, data)

  # the command names the program's CRC: the CEC stores only that program (PROTOCOLS.md §1
  # "Whole-program check")
  defp start({:download, lines}, from, data) do
    crc = ProgramCRC.compute(lines)

    start_string(
      [{"M", "DOWNLOAD_HP(#{ProgramCRC.format(crc)})"}],
      %{from: from, kind: :commands, then: {:download, lines, crc}},
      data
    )
  end

  defp start(:upload, from, data),
    do: start_string([{"M", "UPLOAD_SUN"}], %{from: from, kind: :commands, then: :upload}, data)

  defp start({:status, name}, from, data) do
    {[{"S", number}], data} = allocate([{"S", name}], data)
    {seq, data} = next_sequence(data)
    line = encode(seq, [{"S", number, name}], data)
    req = %{from: from, kind: :status, seq: seq, line: line, tries: 1, number: number, name: name}
    data = data |> bump(:strings) |> bump(:status_queries)
    data = send_line(data, line, :status_query, "ask #{name}")
    {:next_state, :awaiting_reply, %{data | req: req}}
  end

  defp start_string(commands, req, data) do
    {numbered, data} = allocate(commands, data)
    {seq, data} = next_sequence(data)

    line =
      encode(
        seq,
        Enum.zip_with(numbered, commands, fn {l, n}, {_, text} -> {l, n, text} end),
        data
      )

    req = Map.merge(req, %{seq: seq, line: line, tries: 1, numbered: numbered})

    data =
      data
      |> bump(:strings)
      |> Map.update!(:counters, &%{&1 | commands: &1.commands + length(commands)})

    meaning =
      "string #{pad4(seq)}: " <>
        Enum.map_join(numbered, ", ", fn {l, n} -> "#{set_name(l)} #{pad4(n)}" end)

    data = send_line(data, line, :string, meaning)
    {:next_state, :awaiting_reply, %{data | req: req}}
  end

  defp allocate(commands, data) do
    Enum.map_reduce(commands, data, fn {letter, _text}, data ->
      n = Map.get(data.next, letter, 1)
      {{letter, n}, %{data | next: Map.put(data.next, letter, if(n >= 9999, do: 1, else: n + 1))}}
    end)
  end

  defp next_sequence(data),
    do: {data.next_seq, %{data | next_seq: rem(data.next_seq + 1, 10_000)}}

  defp encode(seq, commands, data) do
    commands =
      for {letter, number, text} <- commands do
        %Command{letter: letter, set: Command.set_for_letter(letter), number: number, text: text}
      end

    %CommandString{sequence: seq, commands: commands}
    |> CommandString.encode(bcc: data.bcc)
    |> IO.iodata_to_binary()
  end

  ## Replies to a string

  defp reply_line({:ok, :nak}, line, data) do
    seq = pad4(data.req.seq)
    data = emit(bump(data, :naks), :received, :nak, line, "E: string #{seq} arrived damaged")
    resend(data, :nak)
  end

  defp reply_line({:ok, {:ack, seq}}, line, %{req: %{kind: :commands, seq: seq} = req} = data) do
    data = emit(data, :received, :ack, line, "ack: string #{pad4(seq)} received intact")

    case req.then do
      nil ->
        :gen_statem.reply(req.from, {:ok, req.numbered})
        {:next_state, :idle, %{data | req: nil}}

      {:download, lines, crc} ->
        [{"M", number}] = req.numbered

        req = %{
          from: req.from,
          number: number,
          crc: crc,
          lines: lines,
          total: length(lines),
          sent: 0,
          tries: 1
        }

        {:next_state, :downloading, %{data | req: req}}

      :upload ->
        [{"M", number}] = req.numbered
        {:next_state, :uploading, %{data | req: %{from: req.from, number: number, received: []}}}
    end
  end

  defp reply_line(
         {:ok, {:status, n, text}},
         line,
         %{req: %{kind: :status, number: n} = req} = data
       ) do
    data = emit(data, :received, :status, line, status_meaning(req.name, text))
    :gen_statem.reply(req.from, {:ok, text})
    {:next_state, :idle, %{data | req: nil}}
  end

  defp reply_line({:ok, _other}, line, data), do: {:keep_state, stray(data, line)}

  defp reply_line({:error, error}, line, data) do
    data = emit(data, :received, :damaged, line, "damaged reply: #{Exception.message(error)}")
    resend(data, :damaged)
  end

  defp resend(%{req: req} = data, cause) do
    if req.tries > data.max_resends do
      reason = if cause == :timeout, do: :timeout, else: :nak
      error = %ClientError{reason: reason, data: %{sequence: req.seq, tries: req.tries}}
      :gen_statem.reply(req.from, {:error, error})
      {:next_state, :idle, %{data | req: nil}}
    else
      tries = req.tries + 1

      data =
        send_line(
          bump(data, :resends),
          req.line,
          :resend,
          "string #{pad4(req.seq)} again (try #{tries} of #{data.max_resends + 1})"
        )

      {:keep_state, %{data | req: %{req | tries: tries}},
       [{:state_timeout, data.reply_timeout, :no_reply}]}
    end
  end

  ## Program lines

  # The line ending the program: `%` (not as the first line) with the program's CRC, `%/cccc`
  # (PROTOCOLS.md §1 "Whole-program check"), or without it as the seed's CEC sends it.
  defp closing_line(text, n) when n > 1 do
    case ProgramCRC.split_closing(text) do
      {:ok, stored, crc} ->
        if String.trim(stored) == "%", do: {:closing, stored, crc}, else: :not_closing

      :error ->
        if String.trim(text) == "%", do: {:closing, text, nil}, else: :not_closing
    end
  end

  defp closing_line(_text, _n), do: :not_closing

  defp upload_closed(%{req: req} = data, lines, crc) do
    ours = ProgramCRC.compute(lines)

    cond do
      crc == nil ->
        data = emit(data, :note, :note, nil, "the closing line named no CRC: not compared")
        :gen_statem.reply(req.from, {:ok, {"M", req.number}, lines})
        {:next_state, :idle, %{data | req: nil}}

      crc == ours ->
        text = "the program's CRC #{ProgramCRC.format(crc)} is the CEC's"
        data = emit(data, :note, :note, nil, text)
        :gen_statem.reply(req.from, {:ok, {"M", req.number}, lines})
        {:next_state, :idle, %{data | req: nil}}

      true ->
        program_crc_failed(data, :upload, crc, ours)
    end
  end

  # The whole program is not the one the other end has (`sent`: the CRC of the program as its
  # sender has it, `stored` of what its receiver took): the request fails here, whatever the
  # CEC's command says. The transfer itself is over, so the link stays.
  defp program_crc_failed(%{req: req} = data, direction, sent, stored) do
    error = %ClientError{
      reason: :program_crc,
      data: %{direction: direction, number: req.number, sent: sent, stored: stored}
    }

    :gen_statem.reply(req.from, {:error, error})
    data = emit(bump(data, :transfers_broken), :note, :note, nil, Exception.message(error))
    {:next_state, :idle, %{data | req: nil}}
  end

  defp resend_program_line(%{req: req} = data, why) do
    n = req.sent + 1

    if req.tries > data.max_resends do
      transfer_failed(data, :download, n, "#{why}, #{req.tries} tries")
    else
      send_program_line(bump(%{data | req: %{req | tries: req.tries + 1}}, :resends))
    end
  end

  # lines are numbered 0001, 0002, …; after 9999 comes 0000 (PROTOCOLS.md §1)
  defp line_number(n), do: rem(n, 10_000)

  defp send_program_line(%{req: req} = data) do
    [text | _] = req.lines
    n = req.sent + 1
    again = if req.tries > 1, do: " again (try #{req.tries})", else: ""
    line = IO.iodata_to_binary(Reply.encode({:line, line_number(n), text}, bcc: data.bcc))

    data =
      send_line(
        bump(data, :lines_sent),
        line,
        :program_line,
        "program line #{n} of #{req.total}#{again}"
      )

    {:keep_state, data, [{:state_timeout, data.line_timeout, :no_answer}]}
  end

  defp damaged_upload_line(data, line, error) do
    data =
      emit(data, :received, :damaged, line, "damaged program line: #{Exception.message(error)}")

    data = answer_line(bump(data, :naks_sent), :nak, "E: send that line again").data
    {:keep_state, data, [{:state_timeout, data.line_timeout, :no_line}]}
  end

  defp answer_line(data, answer, meaning) do
    reply = if answer == :nak, do: :nak, else: {:line_ack, answer}
    bytes = IO.iodata_to_binary(Reply.encode(reply, bcc: data.bcc))
    %{data: send_line(data, bytes, :line_answer, meaning), bytes: bytes}
  end

  defp transfer_failed(%{req: req} = data, direction, line, why) do
    error = %ClientError{
      reason: :transfer_failed,
      data: %{direction: direction, line: line, why: why}
    }

    :gen_statem.reply(req.from, {:error, error})

    data =
      emit(
        bump(%{data | req: nil}, :transfers_broken),
        :note,
        :link,
        nil,
        "#{direction} broke off at line #{line} (#{why}): reopening the link so the CEC abandons it"
      )

    case reopen(data) do
      {:ok, data} -> {:next_state, :idle, data}
      {:error, data} -> {:next_state, :disconnected, data}
    end
  end

  ## The link

  defp reopen(data) do
    if data.conn, do: Transport.close(data.conn)
    data = %{data | conn: nil, decoder: LineDecoder.new(max_line: @max_line)}

    case Vws.CEC.Cell.connect(data.endpoint) do
      {:ok, conn} ->
        Transport.activate(conn)
        data = bump(%{data | conn: conn}, :reconnects)

        {:ok,
         emit(data, :note, :link, nil, "link to the CEC opened again (#{Transport.peer(conn)})")}

      {:error, reason} ->
        {:error, emit(data, :note, :link, nil, "cannot open the link: #{inspect(reason)}")}
    end
  end

  defp link_down(data, why) do
    data = emit(data, :note, :link, nil, "link to the CEC closed (#{why})")
    if data.req, do: :gen_statem.reply(data.req.from, {:error, %ClientError{reason: :closed}})
    if data.conn, do: Transport.close(data.conn)

    {:next_state, :disconnected,
     %{data | conn: nil, req: nil, decoder: LineDecoder.new(max_line: @max_line)}}
  end

  defp send_line(data, bytes, kind, meaning) do
    data = emit(data, :sent, kind, String.trim_trailing(bytes, "\r\n"), meaning)

    case data.conn && Transport.send(data.conn, bytes) do
      :ok -> data
      nil -> emit(data, :note, :link, nil, "not sent: no link")
      {:error, reason} -> emit(data, :note, :link, nil, "not sent: #{inspect(reason)}")
    end
  end

  ## Everything else, in every state

  defp common({:call, from}, :activate, data) do
    if data.conn, do: Transport.activate(data.conn)
    {:keep_state_and_data, [{:reply, from, :ok}]}
  end

  defp common({:call, from}, {:subscribe, pid}, data),
    do: {:keep_state, add_subscriber(data, pid), [{:reply, from, :ok}]}

  defp common({:call, from}, {:note, text}, data),
    do: {:keep_state, emit(data, :note, :note, nil, text), [{:reply, from, :ok}]}

  defp common({:call, from}, :log, data),
    do: {:keep_state_and_data, [{:reply, from, :queue.to_list(data.log)}]}

  defp common({:call, from}, :info, data) do
    info = %{
      endpoint: data.endpoint,
      peer: data.conn && Transport.peer(data.conn),
      next_sequence: data.next_seq,
      next_numbers: data.next,
      counters: data.counters
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  defp common({:call, from}, other, _data),
    do: {:keep_state_and_data, [{:reply, from, {:error, {:unknown_call, other}}}]}

  defp common(:internal, {:line, line}, %{last_closing: {line, answer}} = data) do
    data = emit(bump(data, :lines_again), :received, :program_line, line, "closing line again")
    {:keep_state, send_line(data, answer, :line_answer, "answered again: stored already")}
  end

  defp common(:internal, {:line, line}, data), do: {:keep_state, stray(data, line)}

  defp common(:internal, {:line_error, error}, data) do
    {:keep_state,
     emit(
       bump(data, :stray),
       :received,
       :damaged,
       nil,
       "line discarded: #{Exception.message(error)}"
     )}
  end

  defp common(:info, {:DOWN, ref, :process, pid, _}, data) do
    case data.subscribers do
      %{^pid => ^ref} -> {:keep_state, %{data | subscribers: Map.delete(data.subscribers, pid)}}
      _ -> :keep_state_and_data
    end
  end

  defp common(:info, msg, %{conn: conn} = data) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        {lines, decoder} = LineDecoder.feed(data.decoder, bytes)
        Transport.activate(conn)

        events =
          for item <- lines do
            case item do
              {:error, error} -> {:next_event, :internal, {:line_error, error}}
              line -> {:next_event, :internal, {:line, line}}
            end
          end

        {:keep_state, %{data | decoder: decoder}, events}

      :closed ->
        link_down(data, "closed by the CEC")

      {:error, reason} ->
        link_down(data, inspect(reason))

      :unknown ->
        Logger.debug("WC client ignored #{inspect(msg, limit: 10)}")
        :keep_state_and_data
    end
  end

  defp common(type, content, _data) do
    Logger.debug("WC client ignored #{inspect(type)} #{inspect(content, limit: 10)}")
    :keep_state_and_data
  end

  ## Event log

  defp emit(data, direction, kind, line, meaning) do
    event = %Event{
      at: System.monotonic_time(:millisecond) - data.t0,
      direction: direction,
      line: line,
      kind: kind,
      meaning: meaning
    }

    for {pid, _ref} <- data.subscribers, do: send(pid, {:wc_client, self(), event})
    log = :queue.in(event, data.log)

    if data.log_size >= @log_length,
      do: %{data | log: :queue.drop(log)},
      else: %{data | log: log, log_size: data.log_size + 1}
  end

  defp stray(data, line) do
    emit(bump(data, :stray), :received, :stray, line, "not the reply awaited: ignored")
  end

  defp add_subscriber(data, pid) do
    if Map.has_key?(data.subscribers, pid),
      do: data,
      else: %{data | subscribers: Map.put(data.subscribers, pid, Process.monitor(pid))}
  end

  ## Helpers

  defp status_meaning(name, text) do
    if String.ends_with?(name, "_CMD") do
      set = String.replace_suffix(name, "_CMD", "")

      case Vws.Peers.WC.Client.command_status(text) do
        {:ok, 0, "NONE"} -> "#{set}: no command yet"
        {:ok, n, word} -> "#{set} #{pad4(n)} #{word}"
        :error -> "#{name}: #{text}"
      end
    else
      "#{name}: #{text}"
    end
  end

  defp set_name("R"), do: "ROBOT"
  defp set_name("M"), do: "MONARCH"
  defp set_name("F"), do: "FIXTURE"
  defp set_name("H"), do: "HYDRAULIC"
  defp set_name("G"), do: "GRIPPER"
  defp set_name("V"), do: "VACUUM"
  defp set_name(letter), do: letter

  defp bump(data, key), do: %{data | counters: Map.update!(data.counters, key, &(&1 + 1))}
end
