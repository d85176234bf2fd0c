defmodule Vws.Links.RS232.Link do
  @moduledoc false
  # The process behind Vws.Links.RS232 (see there for the protocol and the options).
  #
  # States: :disconnected, :idle, :sending (a program goes out, paced, stopped by XOFF),
  # :awaiting (a program from the control: an upload, or a download's read-back). Timers:
  # {:timeout, :pace} the next chunk, {:timeout, :xoff} the longest XOFF, {:timeout, :dc1} the
  # wait for the control's DC1, {:timeout, :program} the wait for a program.

  @behaviour :gen_statem
  require Logger

  alias Vws.Links.{Connection, Endpoint}
  alias Vws.Links.DNC.{Frame, Program}
  alias Vws.Links.RS232.Framing

  @dc1 0x11
  @dc3 0x13

  @defaults [
    framing: [],
    wait_dc1: false,
    dc1_timeout: 10_000,
    xoff_timeout: 10_000,
    verify: :read_back,
    read_back_timeout: 30_000,
    upload_timeout: 120_000,
    baud: 9600,
    chunk: 8,
    max_text: 256,
    connect_timeout: 2_000,
    backoff_min: 100,
    backoff_max: 5_000
  ]

  defp schema do
    [
      name: [type: :any],
      owner: [type: :any],
      endpoint: [type: {:or, [nil, {:custom, &Connection.check_endpoint/1}]}],
      connect: [type: :keyword_list],
      framing: [type: :keyword_list],
      wait_dc1: [type: :boolean],
      verify: [type: {:in, [:read_back, :none]}],
      baud: [type: {:in, Endpoint.bauds()}]
    ] ++
      for key <-
            [:dc1_timeout, :xoff_timeout, :read_back_timeout, :upload_timeout] ++
              [:chunk, :max_text, :connect_timeout],
          do: {key, [type: :pos_integer]}
  end

  defstruct [
    :name,
    :owner,
    :opts,
    :framing,
    :decoder,
    :wire,
    :job,
    :cps,
    xoff: false,
    dc1_seen: false,
    reconnect_in: 0,
    counters: %{
      xoffs: 0,
      programs_sent: 0,
      programs_received: 0,
      bytes_sent: 0,
      bytes_received: 0,
      damaged_received: 0,
      last_error: nil
    }
  ]

  def start_link(opts) do
    opts =
      Vws.Options.validate!(
        opts,
        schema() ++
          [backoff_min: [type: :non_neg_integer], backoff_max: [type: :non_neg_integer]],
        "RS-232 link"
      )

    case Framing.new(Keyword.get(opts, :framing, [])) do
      {:ok, _} -> :ok
      {:error, message} -> raise ArgumentError, "RS-232 link: " <> message
    end

    # the link must see the control's DC1/DC3 to bound an XOFF: a driver or terminal server
    # doing XON/XOFF itself would take them (docs/serial.md)
    with endpoint when endpoint != nil <- opts[:endpoint],
         {:ok, %Endpoint{serial: serial}} <- Endpoint.parse(to_string(endpoint)),
         :xonxoff <- serial[:flow] do
      raise ArgumentError,
            "RS-232 link: #{endpoint} has flow=xonxoff, which makes the tty driver or terminal " <>
              "server take the control's XON/XOFF; this link does XON/XOFF itself (and bounds an " <>
              "XOFF's wait): give flow=none"
    end

    case Keyword.get(opts, :name) do
      nil -> :gen_statem.start_link(__MODULE__, opts, [])
      name -> :gen_statem.start_link(name, __MODULE__, opts, [])
    end
  end

  @impl true
  def callback_mode, do: [:handle_event_function, :state_enter]

  @impl true
  def init(opts) do
    o = Keyword.merge(@defaults, opts)
    {:ok, framing} = Framing.new(o[:framing])
    name = o[:name] || self()
    Logger.metadata(rs232_link: name, workstation: Vws.Names.id_of(o[:name]))

    data = %__MODULE__{
      name: name,
      owner: o[:owner],
      opts: Map.new(o),
      framing: framing,
      decoder: Framing.decoder(framing),
      cps: div(baud(o), 10),
      wire:
        Connection.new(
          endpoint: o[:endpoint],
          backoff: {o[:backoff_min], o[:backoff_max]},
          connect: [timeout: o[:connect_timeout]] ++ Keyword.get(o, :connect, []),
          telemetry: {[:vws, :rs232], %{link: name, workstation: Vws.Names.id_of(name)}},
          report: [:connect_failed, :connected, :disconnected],
          label: "RS-232 DNC link"
        )
    }

    {:ok, :disconnected, data}
  end

  # the line's speed: the endpoint's own setting when it has one, else the option
  defp baud(o) do
    case o[:endpoint] && Endpoint.parse(to_string(o[:endpoint])) do
      {:ok, %Endpoint{serial: [_ | _] = serial}} -> serial[:baud]
      _ -> o[:baud]
    end
  end

  ## Connection

  @impl true
  def handle_event(:enter, _old, :disconnected, %{wire: %{endpoint: nil}}),
    do: :keep_state_and_data

  def handle_event(:enter, _old, :disconnected, data),
    do: {:keep_state_and_data, [{:state_timeout, data.reconnect_in, :connect}]}

  def handle_event(:enter, _old, _state, _data), do: :keep_state_and_data

  def handle_event(:state_timeout, :connect, :disconnected, data),
    do: Connection.dial(data, &connected/1)

  def handle_event({:call, from}, {:attach, conn}, _state, data) do
    data = if data.wire.conn, do: lose(data, :taken_over), else: data
    data = %{data | wire: Connection.attach(data.wire, conn)}
    {:next_state, :idle, connected(data), [{:reply, from, :ok}]}
  end

  def handle_event({:call, from}, :info, state, data) do
    info =
      Map.merge(data.counters, %{
        state: state,
        endpoint: data.wire.endpoint,
        peer: data.wire.peer,
        max_text: data.opts.max_text,
        profile: :rs232_xonxoff,
        xoff: data.xoff,
        transfer: nil,
        counters: Map.delete(data.counters, :last_error)
      })

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  def handle_event({:call, from}, {:set_owner, owner}, _state, data),
    do: {:keep_state, %{data | owner: owner}, [{:reply, from, :ok}]}

  ## Requests

  def handle_event({:call, from}, {:request, _command, _blocks}, :disconnected, _data),
    do: {:keep_state_and_data, [{:reply, from, {:error, "RS-232 LINK DOWN"}}]}

  def handle_event({:call, from}, {:request, command, blocks}, :idle, data) do
    case job(command, blocks, data) do
      {:error, words} ->
        {:keep_state_and_data, [{:reply, from, {:error, words}}]}

      {:send, job} ->
        start_sending(%{data | job: Map.put(job, :from, from)})

      {:receive, job} ->
        await_program(%{data | job: Map.put(job, :from, from)}, data.opts.upload_timeout)
    end
  end

  def handle_event({:call, _from}, {:request, _, _}, _state, _data),
    do: {:keep_state_and_data, [:postpone]}

  ## Sending: the control's DC1 first when asked, then chunks at the line's pace

  def handle_event({:timeout, :dc1}, _, :sending, %{job: %{phase: :dc1}} = data) do
    fail(data, "NO DC1 FROM THE CONTROL WITHIN #{secs(data.opts.dc1_timeout)}")
  end

  def handle_event({:timeout, :pace}, _, :sending, data), do: send_chunk(data)

  def handle_event({:timeout, :xoff}, _, :sending, data) do
    fail(data, "XOFF FROM THE CONTROL FOR OVER #{secs(data.opts.xoff_timeout)}")
  end

  def handle_event({:timeout, :program}, _, :awaiting, %{job: job} = data) do
    s = secs(job.wait)

    words =
      if job.kind == :read_back,
        do: "PROGRAM NOT VERIFIED NO READ BACK WITHIN #{s}",
        else: "NO PROGRAM FROM THE CONTROL WITHIN #{s}"

    fail(data, words)
  end

  def handle_event({:timeout, _}, _, _state, _data), do: :keep_state_and_data

  ## Bytes from the control

  def handle_event(:info, msg, state, data) do
    case Connection.handle_message(data.wire, msg) do
      {:data, bytes} ->
        data = count(data, :bytes_received, byte_size(bytes))
        received(state, bytes, data)

      {:closed, reason} ->
        data = lose(data, reason)
        {:next_state, :disconnected, data, cancel_timers()}

      :unknown ->
        Logger.debug("RS-232 link ignored #{inspect(msg, limit: 5)}")
        :keep_state_and_data
    end
  end

  def handle_event({:call, from}, other, _state, _data) do
    Logger.warning("RS-232 link: unknown call #{inspect(other, limit: 5)}")
    {:keep_state_and_data, [{:reply, from, {:error, :unknown_call}}]}
  end

  def handle_event(type, content, state, _data) do
    Logger.debug("RS-232 link: #{inspect({type, content}, limit: 5)} unexpected in #{state}")
    :keep_state_and_data
  end

  ## What a request is on this line

  defp job(%Frame.Command{direction: :send, operation: op} = command, blocks, data)
       when op in [:part_program, :download_execute] do
    text = IO.iodata_to_binary(blocks)

    cond do
      not Program.complete?(text) ->
        {:error, "PROGRAM HAS NO CLOSING %"}

      not Program.sendable?(text) ->
        {:error, "PROGRAM HOLDS A CONTROL CHARACTER"}

      true ->
        wire = IO.iodata_to_binary(Framing.encode(text, data.framing))

        {:send,
         %{
           kind: op,
           command: command,
           text: text,
           left: wire,
           sent: 0,
           started: now(),
           paced_from: nil,
           paced_sent: 0
         }}
    end
  end

  defp job(%Frame.Command{direction: :receive, operation: :part_program} = command, _, _data),
    do: {:receive, %{kind: :upload, command: command, started: now()}}

  defp job(%Frame.Command{operation: op}, _blocks, _data), do: {:error, cannot(op)}

  defp cannot(:status), do: "NO STATUS REPORT FROM AN RS-232 CONTROL"
  defp cannot(:directory), do: "NO DIRECTORY ON AN RS-232 CONTROL"
  defp cannot(:table), do: "NO TOOL-OFFSET TABLE FROM AN RS-232 CONTROL"
  defp cannot(:remote_control), do: "NO REMOTE PROGRAM SELECT ON AN RS-232 CONTROL"
  defp cannot(:delete), do: "NO REMOTE DELETE ON AN RS-232 CONTROL"
  defp cannot(_other), do: "NOT POSSIBLE ON AN RS-232 CONTROL"

  defp start_sending(data) do
    job = data.job

    cond do
      data.opts.wait_dc1 and not data.dc1_seen ->
        job = Map.put(job, :phase, :dc1)

        {:next_state, :sending, %{data | job: job},
         [{{:timeout, :dc1}, data.opts.dc1_timeout, :dc1}]}

      true ->
        job = Map.merge(job, %{phase: :sending, paced_from: now()})
        # a control still holding the line (XOFF) is waited for, as long as an XOFF may last
        xoff = if data.xoff, do: [{{:timeout, :xoff}, data.opts.xoff_timeout, :xoff}], else: []

        {:next_state, :sending, %{data | job: job, dc1_seen: false},
         [{{:timeout, :pace}, 0, :go} | xoff]}
    end
  end

  defp send_chunk(%{xoff: true}), do: :keep_state_and_data
  defp send_chunk(%{job: %{phase: :dc1}}), do: :keep_state_and_data

  defp send_chunk(%{job: %{left: <<>>}} = data), do: sent_all(data)

  defp send_chunk(data) do
    job = data.job
    n = min(data.opts.chunk, byte_size(job.left))
    <<chunk::binary-size(n), left::binary>> = job.left

    case Connection.send(data.wire, chunk) do
      :ok ->
        job = %{job | left: left, sent: job.sent + n}
        data = count(%{data | job: job}, :bytes_sent, n)
        # the transfer's progress, every 256 bytes and at the last one
        if div(job.sent, 256) != div(job.sent - n, 256) or left == <<>>, do: progress(data, false)
        # the next chunk when the line has carried this one (its pace since sending (re)started)
        {data, due} = pace(data, n)
        {:keep_state, data, [{{:timeout, :pace}, max(due - now(), 0), :go}]}

      {:error, _} ->
        # the connection's end comes as a message: the request ends there
        :keep_state_and_data
    end
  end

  # When the next chunk is due. A sender held up (a loaded host) catches up at most two chunks:
  # beyond that the pace starts again from this chunk, as a UART would go on at its rate —
  # catching up a long delay at once sent a burst the control's buffer could not take before its
  # XOFF came back (buffer overruns in a loaded full suite).
  defp pace(%{job: job} = data, n) do
    now = now()
    due = job.paced_from + div((job.sent - job.paced_sent) * 1000, data.cps)

    if due < now - div(2 * data.opts.chunk * 1000, data.cps) do
      job = %{job | paced_from: now, paced_sent: job.sent - n}
      {%{data | job: job}, now + div(n * 1000, data.cps)}
    else
      {data, due}
    end
  end

  # every byte is out: a drip feed is over; a download waits for its read-back
  defp sent_all(%{job: %{kind: :download_execute}} = data) do
    transfer(data, :out, :ok)
    data = count(data, :programs_sent, 1)
    reply(data, {:ok, []})
  end

  defp sent_all(data) do
    data = count(data, :programs_sent, 1)

    if data.opts.verify == :read_back do
      job = data.job |> Map.put(:kind, :read_back)
      await_program(%{data | job: job}, data.opts.read_back_timeout)
    else
      transfer(data, :out, :ok)
      reply(data, {:ok, []})
    end
  end

  defp await_program(data, wait) do
    {:next_state, :awaiting, %{data | job: Map.put(data.job, :wait, wait)},
     [{{:timeout, :program}, wait, :program}]}
  end

  ## Received bytes: flow control first, then programs

  defp received(state, bytes, data) do
    {data, actions} = flow(bytes, state, data)
    {events, decoder} = Framing.decode(data.decoder, bytes)
    data = %{data | decoder: decoder}

    Enum.reduce(events, {:keep_state, data, actions}, fn event, acc ->
      program_event(event, acc)
    end)
  end

  # the last of DC1/DC3 in a chunk says where the flow stands
  defp flow(bytes, state, data) do
    xoffs = bytes |> :binary.matches(<<@dc3>>) |> length()
    data = if xoffs > 0, do: count(data, :xoffs, xoffs), else: data

    for _ <- 1..xoffs//1,
        do: Vws.Telemetry.execute([:vws, :rs232, :xoff], %{count: 1}, %{link: data.name})

    last =
      bytes
      |> :binary.bin_to_list()
      |> Enum.reverse()
      |> Enum.find(&(&1 in [@dc1, @dc3]))

    case {last, state} do
      {nil, _} ->
        {data, []}

      {@dc3, :sending} ->
        # already stopped: the XOFF's wait keeps its first start
        if data.xoff do
          {data, []}
        else
          job = Map.update(data.job, :pauses, 1, &(&1 + 1))
          {%{data | xoff: true, job: job}, [{{:timeout, :xoff}, data.opts.xoff_timeout, :xoff}]}
        end

      {@dc3, _} ->
        {%{data | xoff: true}, []}

      {@dc1, :sending} ->
        data = %{data | xoff: false, dc1_seen: true}

        case data.job do
          %{phase: :dc1} ->
            job = data.job |> Map.merge(%{phase: :sending, paced_from: now(), paced_sent: 0})

            {%{data | job: job, dc1_seen: false},
             [{{:timeout, :dc1}, :cancel}, {{:timeout, :pace}, 0, :go}]}

          job ->
            # the pace starts again from here: the pause is not made up for at once
            job = %{job | paced_from: now(), paced_sent: job.sent}
            {%{data | job: job}, [{{:timeout, :xoff}, :cancel}, {{:timeout, :pace}, 0, :go}]}
        end

      {@dc1, _} ->
        {%{data | xoff: false, dc1_seen: true}, []}
    end
  end

  defp program_event({:program, text}, {_, data, actions} = acc) do
    data = count(data, :programs_received, 1)

    case data.job do
      %{kind: :read_back, text: ^text} ->
        transfer(data, :out, :ok)
        with_actions(reply(data, {:ok, []}), actions)

      %{kind: :read_back} ->
        with_actions(fail(data, "PROGRAM VERIFY FAILED READ BACK DIFFERS"), actions)

      %{kind: :upload, command: command} ->
        case Program.file_name(Program.from_text(text)) do
          {:ok, file} when file == command.text or command.text == "" ->
            transfer(data, :in, :ok, byte_size(text))
            with_actions(reply(data, {:ok, [text]}), actions)

          {:ok, file} ->
            with_actions(fail(data, "CONTROL SENT #{file} NOT #{command.text}"), actions)

          {:error, _} ->
            with_actions(fail(data, "PROGRAM FROM THE CONTROL HAS NO PROGRAM NUMBER"), actions)
        end

      _ ->
        unasked(data, text)
        put_elem(acc, 1, data)
    end
  end

  defp program_event({:error, reason}, {_, data, actions} = acc) do
    data = count(data, :damaged_received, 1)

    words =
      "PROGRAM FROM THE CONTROL DAMAGED #{reason |> Atom.to_string() |> String.upcase() |> String.replace("_", " ")}"

    case data.job do
      %{kind: kind} when kind in [:read_back, :upload] ->
        with_actions(fail(data, words), actions)

      _ ->
        Logger.warning("RS-232 link: #{String.downcase(words)}: not kept")
        put_elem(acc, 1, data)
    end
  end

  defp with_actions({:next_state, state, data, more}, actions),
    do: {:next_state, state, data, actions ++ more}

  # the operator punched a program at the control: the owner (MONARCH's monitor) keeps it
  defp unasked(data, text) do
    case Program.file_name(Program.from_text(text)) do
      {:ok, file} ->
        command = %Frame.Command{direction: :send, operation: :part_program, text: file}
        notify(data, {:received, command, [text]})

      {:error, _} ->
        Logger.warning(
          "RS-232 link: a program from the control without a program number: not kept"
        )
    end
  end

  ## Ending a request

  defp reply(data, result) do
    if data.job.kind != :upload do
      progress(data, if(result == {:ok, []}, do: :ok, else: elem(result, 1)))
    end

    {:next_state, :idle, %{data | job: nil}, [{:reply, data.job.from, result} | cancel_timers()]}
  end

  defp fail(data, words) do
    Logger.warning("RS-232 link: #{String.downcase(words)}")
    direction = if data.job.kind == :upload, do: :in, else: :out
    transfer(data, direction, :error)
    data = put_in(data.counters.last_error, words)
    # what is left unsent is dropped: the control's buffer holds part of a program, which it
    # must not run as a whole one (documented: docs/serial.md)
    reply(data, {:error, words})
  end

  # A program's transfer, told to the owner as the DNC link tells it (`{:progress, payload}`,
  # the payload of the workstation's :dnc_progress event, documented in Vws.Links.DNC): MONARCH's
  # monitor publishes it, and a drip feed's says the machine runs. Blocks are `max_text` bytes.
  defp progress(%{job: %{text: text} = job} = data, ended) do
    block = data.opts.max_text
    total = job.sent + byte_size(job.left)
    elapsed = max(now() - job.started, 1)
    cps = div(job.sent * 1000, elapsed)

    program =
      case {job.command.text, Program.file_name(Program.from_text(text))} do
        {"", {:ok, file}} -> file
        {name, _} -> name
      end

    notify(
      data,
      {:progress,
       %{
         link: data.name,
         program: program,
         operation: job.command.operation,
         direction: :out,
         blocks: div(job.sent + block - 1, block),
         total_blocks: div(total + block - 1, block),
         bytes: job.sent,
         total_bytes: total,
         program_bytes: min(job.sent, byte_size(text)),
         total_program_bytes: byte_size(text),
         chars_per_s: cps,
         eta_s: if(cps > 0, do: div(byte_size(job.left), cps), else: nil),
         retries: 0,
         pauses: Map.get(job, :pauses, 0),
         ended: ended
       }}
    )
  end

  defp progress(_data, _ended), do: :ok

  defp cancel_timers,
    do: for(t <- [:pace, :xoff, :dc1, :program], do: {{:timeout, t}, :cancel})

  defp transfer(data, direction, result, bytes \\ nil) do
    job = data.job

    Vws.Telemetry.execute(
      [:vws, :rs232, :transfer],
      %{bytes: bytes || Map.get(job, :sent, 0), duration: now() - job.started},
      %{link: data.name, direction: direction, operation: job.command.operation, result: result}
    )
  end

  defp connected(data) do
    notify(data, :connected)
    %{data | decoder: Framing.decoder(data.framing), xoff: false, dc1_seen: false}
  end

  # the request under way ends LINK DOWN; the connection is closed and dialled again later
  defp lose(data, reason) do
    data =
      case data.job do
        nil ->
          data

        job ->
          direction = if job.kind == :upload, do: :in, else: :out
          transfer(data, direction, :error)
          :gen_statem.reply(job.from, {:error, "RS-232 LINK DOWN"})
          %{data | job: nil}
      end

    {retry_in, wire} = Connection.lost(data.wire, reason)
    notify(data, :disconnected)
    %{data | wire: wire, reconnect_in: retry_in, xoff: false}
  end

  defp count(data, key, n), do: update_in(data.counters[key], &(&1 + n))

  defp notify(%{owner: nil}, _msg), do: :ok
  defp notify(%{owner: owner}, msg), do: send(owner, {:dnc, self(), msg})

  defp now, do: System.monotonic_time(:millisecond)

  # a wait in words: "10 S", "0.3 S"
  defp secs(ms) when rem(ms, 1000) == 0, do: "#{div(ms, 1000)} S"
  defp secs(ms), do: "#{:erlang.float_to_binary(ms / 1000, decimals: 1)} S"
end
