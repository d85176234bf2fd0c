defmodule Vws.Links.DNC.Link do
  @moduledoc false

  # emits the telemetry its core (Vws.Links.DNC.Session, @telemetry_prefix) returns
  @telemetry_relay true

  @doc false
  def telemetry_relay?, do: @telemetry_relay
  # The process of one DNC Level 2 line; documented in Vws.Links.DNC (its facade). The protocol is
  # Vws.Links.DNC.Session, a pure core: this gen_statem only does the I/O around it — the connection,
  # the timers the core asks for, the caller's deadline, replies and the owner's messages.
  #
  # The gen_statem's state is the core's state (:disconnected, :idle, :bidding, :sending,
  # :turnaround, :receiving, :answering), so the core's state timeouts are gen_statem state
  # timeouts (a change of state cancels them), and requests that arrive while a transmission is
  # in progress are postponed until :idle; while :disconnected they are answered :link_down.
  # The caller's deadline (Vws.Links.Connection) is the generic timeout {:timeout, :request}; a
  # request still postponed when it passes is answered :timeout and never bid for. The
  # connection, its back-off and their telemetry are the shell's (Vws.Links.Connection).

  @behaviour :gen_statem
  require Logger

  alias Vws.Links.Connection
  alias Vws.Links.DNC.{LinkError, Session}

  @defaults [
    role: :cec,
    owner: nil,
    endpoint: nil,
    reply_timeout: 3_000,
    max_naks: 3,
    max_enqs: 3,
    wack_delay: 2_000,
    max_wacks: 3,
    max_contention: 3,
    response_timeout: 10_000,
    receive_timeout: 10_000,
    answer_timeout: 5_000,
    max_text: 256,
    max_receive: 4 * 1024 * 1024,
    receive_buffer: :infinity,
    connect_timeout: 2_000,
    backoff_min: 100,
    backoff_max: 5_000
  ]

  # the transfers whose progress is published: NC programs (not the status reads)
  @programs [:part_program, :download_execute]

  @doc false
  def defaults, do: @defaults

  defstruct [
    :name,
    :owner,
    :role,
    :limits,
    :wire,
    :req,
    :session,
    progress: nil,
    reconnect_in: 0
  ]

  ## Start

  # Vws.Options: checked in the caller, before the process starts (a function: a captured
  # function in an attribute would be a compile-time dependency)
  defp schema do
    [
      name: [type: :any],
      owner: [type: :any],
      endpoint: [type: {:or, [nil, {:custom, &Connection.check_endpoint/1}]}],
      connect: [type: :keyword_list],
      role: [type: {:in, [:cec, :ge]}],
      pad: [type: :boolean],
      win_contention: [type: :boolean]
    ] ++
      for(
        key <- [:reply_timeout, :response_timeout, :receive_timeout, :answer_timeout],
        do: {key, [type: :pos_integer]}
      ) ++
      for(
        key <- [:max_naks, :max_enqs, :max_wacks, :max_contention, :wack_delay],
        do: {key, [type: :non_neg_integer]}
      ) ++
      [
        max_text: [type: :pos_integer],
        max_receive: [type: :pos_integer],
        receive_buffer: [type: {:or, [:non_neg_integer, {:in, [:infinity]}]}],
        connect_timeout: [type: :pos_integer],
        backoff_min: [type: :non_neg_integer],
        backoff_max: [type: :non_neg_integer]
      ]
  end

  @doc false
  def start_link(opts) do
    opts = Vws.Options.validate!(opts, schema(), "DNC link")

    if Keyword.get(opts, :backoff_min, 100) > Keyword.get(opts, :backoff_max, 5_000),
      do: raise(ArgumentError, "DNC link: backoff_min is over backoff_max")

    case Keyword.get(opts, :name) do
      nil -> :gen_statem.start_link(__MODULE__, opts, [])
      name -> :gen_statem.start_link(name, __MODULE__, opts, [])
    end
  end

  @impl true
  def callback_mode, do: [:handle_event_function, :state_enter]

  @impl true
  def init(opts) do
    # checked by Vws.Links.DNC.start_link/1 (Vws.Options)
    o = Keyword.merge(@defaults, opts)
    role = o[:role]

    Logger.metadata(
      dnc_link: o[:name] || self(),
      dnc_role: role,
      workstation: Vws.Names.id_of(o[:name])
    )

    limits =
      Map.new(Keyword.drop(o, [:name, :owner, :endpoint, :connect, :role, :pad, :win_contention]))

    session =
      Session.new([role: role, limits: limits] ++ Keyword.take(opts, [:pad, :win_contention]))

    name = o[:name] || self()

    data = %__MODULE__{
      name: name,
      owner: o[:owner],
      role: role,
      limits: limits,
      wire:
        Connection.new(
          endpoint: o[:endpoint],
          backoff: {o[:backoff_min], o[:backoff_max]},
          connect: [timeout: o[:connect_timeout]] ++ Keyword.get(o, :connect, []),
          telemetry:
            {[:vws, :dnc], %{link: name, role: role, workstation: Vws.Names.id_of(name)}},
          report: [:connect_failed, :connected, :disconnected],
          label: "DNC link"
        ),
      session: session
    }

    {:ok, :disconnected, data}
  end

  ## :disconnected — (re)connecting with backoff, or waiting to be given a connection

  @impl true
  def handle_event(:enter, _old, :disconnected, %{wire: %{endpoint: nil}}),
    do: :keep_state_and_data

  # The first dial goes at once; after a lost connection, the wait the shell gave (it doubles
  # until the peer has sent a frame on a connection, see Vws.Links.Backoff).
  def handle_event(:enter, _old, :disconnected, data),
    do: {:keep_state_and_data, [{:state_timeout, data.reconnect_in, :connect}]}

  def handle_event(:enter, _old, _state, _data), do: :keep_state_and_data

  def handle_event(:state_timeout, :connect, :disconnected, data),
    do: Connection.dial(data, &take_connection/1)

  # Vws.Links.DNC.request/4: the caller's deadline comes with it (Vws.Links.Connection)
  def handle_event(:cast, {Connection, _, _, _} = call, _state, _data),
    do: {:keep_state_and_data, [Connection.as_call(call)]}

  def handle_event({:call, from}, {:deadline, _, {:request, _, _}}, :disconnected, _data) do
    {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :link_down}}}]}
  end

  ## Requests, answers and unsolicited text: only while :idle (postponed otherwise)

  def handle_event({:call, from}, {:deadline, deadline, {:request, command, blocks}}, :idle, data) do
    if Connection.expired?(deadline) do
      # it waited its whole time for the line: never bid for
      {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :timeout}}}]}
    else
      case Session.request(data.session, command, blocks, now()) do
        {:error, :invalid_text} ->
          {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :invalid_text}}}]}

        result ->
          ref = make_ref()
          req = %{from: from, ref: ref, command: command}

          timer =
            if deadline == :infinity,
              do: [],
              else: [{{:timeout, :request}, Connection.remaining(deadline), ref}]

          apply_result(%{data | req: req}, result, timer)
      end
    end
  end

  def handle_event({:call, _from}, {:deadline, _, {:request, _, _}}, _state, _data),
    do: {:keep_state_and_data, [:postpone]}

  def handle_event({:call, from}, {:transmit, blocks}, :idle, data) do
    case Session.transmit(data.session, blocks, now()) do
      {:error, reason} -> {:keep_state_and_data, [{:reply, from, {:error, reason}}]}
      result -> apply_result(data, result, [{:reply, from, :ok}])
    end
  end

  def handle_event({:call, _from}, {:transmit, _}, state, _data) when state != :disconnected,
    do: {:keep_state_and_data, [:postpone]}

  def handle_event(:internal, {:transmit, blocks}, :idle, data) do
    case Session.transmit(data.session, blocks, now()) do
      {:error, _reason} -> :keep_state_and_data
      result -> apply_result(data, result, [])
    end
  end

  def handle_event({:call, from}, {:answer, ref, blocks}, _state, data) do
    case Session.answer(data.session, ref, blocks, now()) do
      {:error, :not_asked} ->
        {:keep_state_and_data, [{:reply, from, {:error, :not_asked}}]}

      {:error, :invalid_text} ->
        {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :invalid_text}}}]}

      result ->
        apply_result(data, result, [{:reply, from, :ok}])
    end
  end

  ## Events every state handles alike

  def handle_event({:call, from}, :info, state, data) do
    session = data.session

    info = %{
      state: state,
      role: data.role,
      endpoint: data.wire.endpoint,
      peer: data.wire.peer,
      max_text: data.limits.max_text,
      counters: Session.counters(session),
      transfer: Vws.Links.DNC.Progress.of(session, now())
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  def handle_event({:call, from}, {:set_owner, owner}, _state, data),
    do: {:keep_state, %{data | owner: owner}, [{:reply, from, :ok}]}

  def handle_event({:call, from}, {:grant, bytes}, _state, data),
    do:
      {:keep_state, %{data | session: Session.grant(data.session, bytes)}, [{:reply, from, :ok}]}

  def handle_event({:call, from}, {:attach, conn}, _state, data) do
    data =
      if Connection.connected?(data.wire) do
        Logger.warning("DNC: a new connection takes over from #{data.wire.peer}, which is closed")
        lose_connection(data, :taken_over)
      else
        data
      end

    data = %{data | wire: Connection.attach(data.wire, conn)}
    {:next_state, :idle, take_connection(data), [{:reply, from, :ok}]}
  end

  def handle_event({:call, from}, other, _state, data) do
    Logger.warning("DNC: unknown call #{inspect(other, limit: 5)}")
    data = %{data | session: Session.unexpected(data.session)}
    {:keep_state, data, [{:reply, from, {:error, :unknown_call}}]}
  end

  def handle_event({:timeout, :request}, ref, _state, %{req: %{ref: ref}} = data) do
    apply_result(data, Session.handle_timeout(data.session, :request, now()), [])
  end

  def handle_event({:timeout, :request}, _stale, _state, _data), do: :keep_state_and_data

  # The owner did not answer the peer's R command within answer_timeout: the session says so and
  # goes idle. Where the owner was meanwhile goes into the log beside it: that is where an
  # operator finds why (an owner held up by a slow disk, or by a call that waits for this line).
  def handle_event(:state_timeout, :answer, _state, data) do
    Logger.warning(
      "DNC: the peer's R command was waiting for the link's owner, #{owner_at(data.owner)}"
    )

    apply_result(data, Session.handle_timeout(data.session, :answer, now()), [])
  end

  def handle_event(:state_timeout, tag, _state, data) do
    apply_result(data, Session.handle_timeout(data.session, tag, now()), [])
  end

  def handle_event(:info, msg, _state, data) do
    case Connection.handle_message(data.wire, msg) do
      {:data, bytes} ->
        apply_result(data, Session.handle_bytes(data.session, bytes, now()), [])

      {:closed, reason} ->
        {:next_state, :disconnected, lose_connection(data, reason)}

      :unknown ->
        Logger.debug("DNC link ignored #{inspect(msg, limit: 5)}")
        :keep_state_and_data
    end
  end

  def handle_event(type, content, state, data) do
    Logger.debug("DNC: #{inspect({type, content}, limit: 5)} unexpected in state #{state}")
    {:keep_state, %{data | session: Session.unexpected(data.session)}}
  end

  defp apply_result(data, {session, output, events}, actions) do
    data = %{data | session: session}
    data = Enum.reduce(output, data, &send_bytes(&2, &1))
    {data, actions} = Enum.reduce(events, {data, actions}, &carry_out/2)
    {:next_state, Session.state(session), publish_progress(data), actions}
  end

  ## Progress of an NC program's transfer: telemetry and the workstation's :dnc_progress event

  defp publish_progress(data) do
    progress =
      case Vws.Links.DNC.Progress.of(data.session, now()) do
        %{command: %{operation: op}} = p when op in @programs -> p
        _ -> nil
      end

    case {data.progress, progress} do
      {nil, nil} ->
        data

      {_last, nil} ->
        # its end was told by the core's {:transfer_end, …}
        %{data | progress: nil}

      {last, p} ->
        if last == nil or {last.blocks, last.direction} != {p.blocks, p.direction},
          do: publish(data, p, false)

        %{data | progress: p}
    end
  end

  # the payload of {:vws_event, ws, :dnc_progress, payload}, documented in Vws.Links.DNC
  # ended: false while it runs; at its end, its result (:ok or the reason it failed)
  defp publish(data, p, ended) do
    payload = %{
      link: data.name,
      program: p.program,
      operation: p.command.operation,
      direction: p.direction,
      blocks: p.blocks,
      total_blocks: p.total_blocks,
      bytes: p.bytes,
      total_bytes: p.total_bytes,
      program_bytes: p.program_bytes,
      total_program_bytes: p.total_program_bytes,
      chars_per_s: p.chars_per_s,
      eta_s: p.eta_s,
      retries: p.retries,
      pauses: p.pauses,
      ended: ended
    }

    emit(
      data,
      :progress,
      Map.drop(payload, [:link, :blocks, :bytes, :program_bytes, :chars_per_s, :retries, :pauses]),
      Map.take(payload, [:blocks, :bytes, :program_bytes, :chars_per_s, :retries, :pauses])
    )

    # the link's owner (in a workstation, MONARCH's monitor) publishes it on the workstation's
    # pub/sub: a link knows no workstation
    notify(data, {:progress, payload})
  end

  defp carry_out({:state_timeout, ms, tag}, {data, actions}),
    do: {data, actions ++ [{:state_timeout, ms, tag}]}

  defp carry_out({:reply, result}, {%{req: %{from: from}} = data, actions}),
    do: {%{data | req: nil}, actions ++ [{:reply, from, result}]}

  defp carry_out({:reply, _result}, acc), do: acc

  defp carry_out({:notify, msg}, {data, actions}) do
    notify(data, msg)

    case msg do
      {:unsolicited, blocks} when data.owner == nil ->
        Logger.info("DNC: unsolicited text from the peer: #{inspect(blocks, limit: 5)}")

      {:request, _ref, command, _blocks} when data.owner == nil ->
        Logger.warning("DNC: R command #{inspect(command)} but no owner to answer it")

      _ ->
        :ok
    end

    {data, actions}
  end

  defp carry_out({:telemetry, name, measurements, metadata}, {data, actions}) do
    relay(data, name, metadata, measurements)
    {data, actions}
  end

  defp carry_out({:log, level, message}, acc) do
    Logger.log(level, message)
    acc
  end

  defp carry_out({:transfer_end, t, result}, {data, actions}) do
    case t.command do
      %{operation: op} when op in @programs ->
        publish(data, Vws.Links.DNC.Progress.describe(t, now()), result)

      _ ->
        :ok
    end

    {data, actions}
  end

  defp carry_out(:peer_alive, {data, actions}),
    do: {%{data | wire: Connection.alive(data.wire)}, actions}

  ## Connection

  defp take_connection(data) do
    notify(data, :connected)
    %{data | session: Session.connected(data.session)}
  end

  # Everything in progress ends :link_down; the connection is closed (its back-off's next wait
  # is taken when :disconnected is entered again).
  defp lose_connection(data, reason) do
    {session, _output, events} = Session.disconnected(data.session, now())
    {data, actions} = Enum.reduce(events, {%{data | session: session}, []}, &carry_out/2)
    for {:reply, from, result} <- actions, do: :gen_statem.reply(from, result)
    {retry_in, wire} = Connection.lost(data.wire, reason)
    notify(data, :disconnected)
    %{data | wire: wire, req: nil, reconnect_in: retry_in}
  end

  defp send_bytes(data, bytes) do
    case Connection.send(data.wire, bytes) do
      :ok -> :ok
      {:error, :not_connected} -> :ok
      {:error, reason} -> Logger.warning("DNC send failed: #{inspect(reason)}")
    end

    data
  end

  ## Helpers

  defp now, do: System.monotonic_time()

  defp owner_at(nil), do: "and there is none"

  defp owner_at(pid) when is_pid(pid) and node(pid) == node() do
    case Process.info(pid, :current_stacktrace) do
      {:current_stacktrace, frames} ->
        "#{inspect(pid)}, at " <>
          Enum.map_join(Enum.take(frames, 4), " < ", &Exception.format_stacktrace_entry/1)

      nil ->
        "#{inspect(pid)}, which is gone"
    end
  end

  defp owner_at(owner), do: inspect(owner)

  defp notify(%{owner: nil}, _msg), do: :ok
  defp notify(%{owner: owner}, msg), do: send(owner, {:dnc, self(), msg})

  defp emit(data, event, metadata, measurements) do
    Vws.Telemetry.execute([:vws, :dnc, event], measurements, link_metadata(data, metadata))
  end

  # what the session core returned (its names are checked at the core: @telemetry_prefix)
  defp relay(data, name, metadata, measurements) do
    Vws.Telemetry.execute([:vws, :dnc, name], measurements, link_metadata(data, metadata))
  end

  defp link_metadata(data, metadata) do
    Map.merge(metadata, %{
      link: data.name,
      role: data.role,
      workstation: Vws.Names.id_of(data.name)
    })
  end
end
