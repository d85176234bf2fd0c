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
  # The caller's deadline is the generic timeout {:timeout, :request}.
  #
  # A `tap` ({module, state}) may stand between the core and the wire: a simulator's fault
  # injection (Vws.Sim.GE2000.Faults). The product never sets one.

  @behaviour :gen_statem
  require Logger

  alias Vws.Links.DNC.{LinkError, Session}
  alias Vws.Links.Transport

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
    :endpoint,
    :role,
    :limits,
    :conn,
    :peer,
    :backoff,
    :req,
    :session,
    tap: nil,
    progress: nil,
    connect_failures: 0
  ]

  ## Start

  @doc false
  def start_link(opts) do
    case Keyword.get(opts, :name) do
      nil -> :gen_statem.start_link(__MODULE__, opts, [])
      name -> :gen_statem.start_link(name, __MODULE__, opts, [])
    end
  end

  @impl true
  def callback_mode, do: [:handle_event_function, :state_enter]

  @impl true
  def init(opts) do
    unknown = Keyword.keys(opts) -- [:name, :pad, :win_contention, :tap | Keyword.keys(@defaults)]

    if unknown != [], do: raise(ArgumentError, "unknown DNC link options #{inspect(unknown)}")

    o = Keyword.merge(@defaults, opts)
    role = o[:role]
    unless role in [:cec, :ge], do: raise(ArgumentError, "role must be :cec or :ge")

    Logger.metadata(
      dnc_link: o[:name] || self(),
      dnc_role: role,
      workstation: Vws.Names.id_of(o[:name])
    )

    limits =
      Map.new(Keyword.drop(o, [:name, :owner, :endpoint, :role, :pad, :win_contention, :tap]))

    session =
      Session.new([role: role, limits: limits] ++ Keyword.take(opts, [:pad, :win_contention]))

    data = %__MODULE__{
      name: o[:name] || self(),
      owner: o[:owner],
      endpoint: o[:endpoint],
      role: role,
      limits: limits,
      tap: o[:tap],
      backoff: Vws.Links.Backoff.new(o[:backoff_min], o[:backoff_max]),
      session: session
    }

    {:ok, :disconnected, data}
  end

  ## :disconnected — (re)connecting with backoff, or waiting to be given a connection

  @impl true
  def handle_event(:enter, _old, :disconnected, %{endpoint: nil}), do: :keep_state_and_data

  # The first dial goes at once; after a lost connection the back-off's next wait (it doubles
  # until the peer has sent a frame on a connection, see Vws.Links.Backoff).
  def handle_event(:enter, _old, :disconnected, data) do
    if Session.counters(data.session).connections == 0 and data.connect_failures == 0 do
      {:keep_state_and_data, [{:state_timeout, 0, :connect}]}
    else
      {wait, backoff} = Vws.Links.Backoff.next(data.backoff)
      {:keep_state, %{data | backoff: backoff}, [{:state_timeout, wait, :connect}]}
    end
  end

  def handle_event(:enter, _old, _state, _data), do: :keep_state_and_data

  def handle_event(:state_timeout, :connect, :disconnected, data) do
    case Transport.connect(data.endpoint, timeout: data.limits.connect_timeout) do
      {:ok, conn} ->
        {:next_state, :idle, take_connection(data, conn)}

      {:error, reason} ->
        failures = data.connect_failures + 1
        level = if failures == 1, do: :warning, else: :debug
        Logger.log(level, "DNC link cannot reach #{data.endpoint}: #{inspect(reason)}; retrying")
        {wait, backoff} = Vws.Links.Backoff.next(data.backoff)
        data = %{data | backoff: backoff, connect_failures: failures}

        emit(data, :connect_failed, %{endpoint: to_string(data.endpoint), reason: reason}, %{
          count: 1,
          retry_in: wait
        })

        {:keep_state, data, [{:state_timeout, wait, :connect}]}
    end
  end

  def handle_event({:call, from}, {:request, _cmd, _blocks, _timeout}, :disconnected, _data) do
    {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :link_down}}}]}
  end

  ## Requests, answers and unsolicited text: only while :idle (postponed otherwise)

  def handle_event({:call, from}, {:request, command, blocks, timeout}, :idle, data) do
    case Session.request(data.session, command, blocks, now()) do
      {:error, :invalid_text} ->
        {:keep_state_and_data, [{:reply, from, {:error, %LinkError{reason: :invalid_text}}}]}

      result ->
        ref = make_ref()
        req = %{from: from, ref: ref, command: command}
        deadline = if timeout == :infinity, do: [], else: [{{:timeout, :request}, timeout, ref}]
        apply_result(%{data | req: req}, result, deadline)
    end
  end

  def handle_event({:call, _from}, {:request, _, _, _}, _state, _data),
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
      endpoint: data.endpoint,
      peer: data.peer,
      fault: tap_fault(data.tap),
      max_text: data.limits.max_text,
      counters: Session.counters(session),
      transfer: Vws.Links.DNC.Progress.of(session, now())
    }

    {:keep_state_and_data, [{:reply, from, info}]}
  end

  def handle_event({:call, from}, {:set_owner, owner}, _state, data),
    do: {:keep_state, %{data | owner: owner}, [{:reply, from, :ok}]}

  def handle_event({:call, from}, {:set_tap, tap}, _state, data),
    do: {:keep_state, %{data | tap: tap}, [{:reply, from, :ok}]}

  def handle_event({:call, from}, {:grant, bytes}, _state, data),
    do:
      {:keep_state, %{data | session: Session.grant(data.session, bytes)}, [{:reply, from, :ok}]}

  def handle_event({:call, from}, {:attach, conn}, _state, data) do
    data =
      if data.conn do
        Logger.warning("DNC: a new connection takes over from #{data.peer}, which is closed")
        old = data.conn
        data = lose_connection(data, :taken_over)
        Transport.close(old)
        data
      else
        data
      end

    {:next_state, :idle, take_connection(data, conn), [{:reply, from, :ok}]}
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

  def handle_event(:state_timeout, tag, _state, data) do
    apply_result(data, Session.handle_timeout(data.session, tag, now()), [])
  end

  def handle_event(:info, msg, state, %{conn: conn} = data) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        received(bytes, data)

      :closed ->
        connection_lost(state, data, :closed)

      {:error, reason} ->
        connection_lost(state, data, reason)

      :unknown ->
        Logger.debug("DNC link ignored #{inspect(msg, limit: 5)}")
        :keep_state_and_data
    end
  end

  def handle_event(type, content, state, data) do
    Logger.debug("DNC: #{inspect({type, content}, limit: 5)} unexpected in state #{state}")
    {:keep_state, %{data | session: Session.unexpected(data.session)}}
  end

  # what a simulator's tap says it does to the line (`describe/1`), for info/1
  defp tap_fault(nil), do: :none

  defp tap_fault({mod, state}) do
    if function_exported?(mod, :describe, 1), do: mod.describe(state), else: mod
  end

  ## The core's results

  defp received(bytes, %{tap: {mod, tap}} = data) do
    {tap, bytes, actions} = mod.incoming(tap, bytes, Session.state(data.session))
    data = %{data | tap: {mod, tap}}
    result = Session.handle_bytes(data.session, bytes, now())
    {data, actions} = tap_actions(data, actions)
    apply_result(data, result, actions)
  end

  defp received(bytes, data),
    do: apply_result(data, Session.handle_bytes(data.session, bytes, now()), [])

  # a tap may make this end bid and send text of its own (a contention of the simulator's)
  defp tap_actions(data, actions) do
    {data, for({:transmit, blocks} <- actions, do: {:next_event, :internal, {:transmit, blocks}})}
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
    do: {%{data | backoff: Vws.Links.Backoff.reset(data.backoff)}, actions}

  ## Connection

  defp take_connection(data, conn) do
    :ok = Transport.activate(conn)
    peer = Transport.peer(conn)
    Logger.info("DNC link connected to #{peer}")
    emit(data, :connected, %{peer: peer})
    notify(data, :connected)

    %{
      data
      | conn: conn,
        peer: peer,
        session: Session.connected(data.session),
        connect_failures: 0
    }
  end

  defp connection_lost(_state, data, reason) do
    Logger.warning("DNC link to #{data.peer} lost: #{inspect(reason)}")
    data = lose_connection(data, reason)
    {:next_state, :disconnected, data}
  end

  # Everything in progress ends :link_down; the connection is dropped.
  defp lose_connection(data, reason) do
    {session, _output, events} = Session.disconnected(data.session, now())
    {data, actions} = Enum.reduce(events, {%{data | session: session}, []}, &carry_out/2)
    for {:reply, from, result} <- actions, do: :gen_statem.reply(from, result)
    emit(data, :disconnected, %{peer: data.peer, reason: reason})
    notify(data, :disconnected)
    %{data | conn: nil, peer: nil, req: nil}
  end

  defp send_bytes(%{conn: nil} = data, _bytes), do: data

  defp send_bytes(%{tap: {mod, tap}} = data, bytes) do
    {tap, out} = mod.outgoing(tap, IO.iodata_to_binary(bytes), Session.transfer(data.session))
    data = %{data | tap: {mod, tap}}
    if out != [], do: transport_send(data, out)
    data
  end

  defp send_bytes(data, bytes) do
    transport_send(data, bytes)
    data
  end

  defp transport_send(data, bytes) do
    case Transport.send(data.conn, bytes) do
      :ok -> :ok
      {:error, reason} -> Logger.warning("DNC send failed: #{inspect(reason)}")
    end
  end

  ## Helpers

  defp now, do: System.monotonic_time()

  defp notify(%{owner: nil}, _msg), do: :ok
  defp notify(%{owner: owner}, msg), do: send(owner, {:dnc, self(), msg})

  defp emit(data, event, metadata, measurements \\ %{count: 1}) do
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
