defmodule Vws.Links.Connection do
  @moduledoc """
  The connection shell every device link shares (`Vws.Links.VAL`, `Vws.Links.DDCMP`,
  `Vws.Links.DNC`, `Vws.Links.HPIB`): the part of a driver that is not its protocol.

  Two halves, both used from the driver's own `:gen_statem`:

    * **The wire** — a struct the driver keeps in its state: the endpoint, the open
      `Vws.Links.Transport` connection, the back-off (`Vws.Links.Backoff`) between dials.
      `connect/1` dials (never call it from `init/1`: make the first dial an event), `attach/2`
      takes a connection someone else opened, `handle_message/2` classifies a message of the
      process (and arms the next chunk), `lost/2` closes and says how long to wait before
      dialling again, `alive/1` tells the back-off the peer answered. It emits
      `[prefix, :connect_failed]` (and, if the driver asks, `:connected` and `:disconnected`)
      and logs the changes, the first failed dial at `:warning` and the ones that follow at
      `:debug` (a peer that stays away fills no log).

    * **Caller deadlines** (as `Redix.Connection` does it) — `call/3` and `send_request/3` send
      the request with the caller's deadline and a reply address that is a process alias;
      the driver honours the deadline (a request whose time has passed is never sent) and
      replies with an ordinary `{:reply, from, reply}` action. The caller stops waiting at its
      deadline, and its alias goes with it: an answer that comes later is dropped by the
      runtime, it never reaches the caller's mailbox. No `timeout + margin`, no
      `catch :exit`. (The alias is a monitor's, `alias: :reply_demonitor`: the caller also
      sees the driver end, and the alias takes one reply at most.)

  A driver takes the requests with one clause that makes them calls again:

      def handle_event(:cast, {Vws.Links.Connection, _, _, _} = call, _state, _data),
        do: {:keep_state_and_data, [Vws.Links.Connection.as_call(call)]}

  which gives it the event `{:call, from}` with content `{:deadline, deadline, request}`.
  """

  require Logger

  alias Vws.Links.{Backoff, Endpoint, Transport}

  # the names are the drivers', checked in their catalogue entries (test/vws/links/connection_test.exs)
  @telemetry_relay true

  @doc false
  def telemetry_relay?, do: @telemetry_relay

  @enforce_keys [:backoff]
  defstruct [
    :endpoint,
    :conn,
    :peer,
    :backoff,
    :label,
    connect: [],
    prefix: nil,
    metadata: %{},
    report: [:connect_failed],
    connects: 0,
    failures: 0,
    last_error: nil
  ]

  @type t :: %__MODULE__{
          endpoint: Endpoint.t() | String.t() | nil,
          conn: Transport.Conn.t() | nil,
          peer: String.t() | nil,
          backoff: Backoff.t(),
          label: String.t() | nil,
          connect: keyword,
          prefix: [atom] | nil,
          metadata: map,
          report: [:connect_failed | :connected | :disconnected],
          connects: non_neg_integer,
          failures: non_neg_integer,
          last_error: term
        }

  @typedoc "A monotonic time in ms (`System.monotonic_time(:millisecond)`), or `:infinity`."
  @type deadline :: integer | :infinity

  @typedoc """
  Where a request's reply goes: a gen_statem `from` whose tag is the caller's alias, the form
  OTP's own calls use since OTP 24 (`gen:reply/2` sends the reply to the alias, not the pid).
  """
  @type from :: {pid, [:alias | reference]}

  @typedoc "A request made by `send_request/3`, for `check_response/2`."
  @opaque request_id :: {reference, deadline}

  ## The wire

  @doc """
  A shell for one link, not connected. Options:

    * `:endpoint` — what `connect/1` dials (a `Vws.Links.Endpoint` or its string); nil for a
      link that is given its connections (`attach/2`);
    * `:backoff` — `{min, max}` ms between dials, doubling (`Vws.Links.Backoff`);
    * `:connect` — options for `Vws.Links.Transport.connect/2` (`timeout:`, `transport:`);
    * `:telemetry` — `{prefix, metadata}`: the driver's event prefix (`[:vws, :dnc]`) and the
      metadata every event carries;
    * `:report` — which state changes are telemetry events: `:connect_failed` (default) and
      `:connected` (metadata `peer`), `:disconnected` (`peer`, `reason`);
    * `:label` — how logs name the link (`"DNC link"`); nil: the shell logs nothing.
  """
  @spec new(keyword) :: t
  def new(opts) do
    {min, max} = Keyword.fetch!(opts, :backoff)
    {prefix, metadata} = Keyword.get(opts, :telemetry, {nil, %{}})

    %__MODULE__{
      endpoint: Keyword.get(opts, :endpoint),
      backoff: Backoff.new(min, max),
      connect: Keyword.get(opts, :connect, []),
      prefix: prefix,
      metadata: metadata,
      report: Keyword.get(opts, :report, [:connect_failed]),
      label: Keyword.get(opts, :label)
    }
  end

  @doc """
  Dials the endpoint. `{:ok, shell}` with the connection open and armed for its first chunk,
  or `{:error, reason, retry_in, shell}`: dial again in `retry_in` ms (the back-off's next wait).
  """
  @spec connect(t) :: {:ok, t} | {:error, term, non_neg_integer, t}
  def connect(%__MODULE__{endpoint: endpoint} = c) when endpoint != nil do
    case Transport.connect(endpoint, c.connect) do
      {:ok, conn} ->
        {:ok, attach(c, conn)}

      {:error, reason} ->
        {wait, backoff} = Backoff.next(c.backoff)
        c = %{c | backoff: backoff, failures: c.failures + 1, last_error: {:connect, reason}}

        if c.label do
          level = if c.failures == 1, do: :warning, else: :debug
          Logger.log(level, "#{c.label} cannot reach #{endpoint}: #{describe(reason)}; retrying")
        end

        emit(c, :connect_failed, %{count: 1, retry_in: wait}, %{
          endpoint: to_string(endpoint),
          reason: reason
        })

        {:error, reason, wait, c}
    end
  end

  @doc """
  A `:disconnected` state's dial for a `:gen_statem` driver whose data keeps this shell in
  `:wire` and dials on the state timeout `:connect`: once connected, `{:next_state, :idle,
  connected.(data)}`; else the next dial after the back-off's wait.
  """
  @spec dial(%{wire: t}, (map -> map)) :: :gen_statem.event_handler_result(atom)
  def dial(%{wire: wire} = data, connected) do
    case connect(wire) do
      {:ok, wire} ->
        {:next_state, :idle, connected.(%{data | wire: wire})}

      {:error, _reason, retry_in, wire} ->
        {:keep_state, %{data | wire: wire}, [{:state_timeout, retry_in, :connect}]}
    end
  end

  @doc """
  Takes an open connection (dialled by `connect/1`, or handed over: the calling process must be
  its controlling process) and arms it for its first chunk.
  """
  @spec attach(t, Transport.Conn.t()) :: t
  def attach(%__MODULE__{} = c, conn) do
    :ok = Transport.activate(conn)
    peer = Transport.peer(conn)
    if c.label, do: Logger.info("#{c.label} connected to #{peer}")
    c = %{c | conn: conn, peer: peer, connects: c.connects + 1, failures: 0, last_error: nil}
    emit(c, :connected, %{count: 1}, %{peer: peer})
    c
  end

  @doc """
  What a message to the process means for the connection: `{:data, bytes}` (the next chunk is
  armed), `{:closed, reason}` (`:closed`, or `{:transport, error}`: call `lost/2`), or
  `:unknown` — not the connection's (also when there is none).
  """
  @spec handle_message(t, term) :: {:data, binary} | {:closed, term} | :unknown
  def handle_message(%__MODULE__{conn: nil}, _message), do: :unknown

  def handle_message(%__MODULE__{conn: conn}, message) do
    case Transport.handle_message(conn, message) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        {:data, bytes}

      :closed ->
        {:closed, :closed}

      {:error, reason} ->
        {:closed, {:transport, reason}}

      :unknown ->
        :unknown
    end
  end

  @doc """
  The connection is gone, or given up (`reason`): it is closed and `{retry_in, shell}` says
  when to dial again (the back-off's next wait; meaningless without an endpoint).
  """
  @spec lost(t, term) :: {non_neg_integer, t}
  def lost(%__MODULE__{} = c, reason) do
    c = close(c)
    if c.label, do: Logger.warning("#{c.label} to #{c.peer} lost: #{describe(reason)}")
    emit(c, :disconnected, %{count: 1}, %{peer: c.peer, reason: reason})
    {wait, backoff} = Backoff.next(c.backoff)
    {wait, %{c | peer: nil, backoff: backoff, last_error: reason}}
  end

  # a transport's error in its words (a tty pulled out says so), anything else as it is
  defp describe(%Transport.Error{} = e), do: Exception.message(e)
  defp describe({:transport, %Transport.Error{} = e}), do: Exception.message(e)
  defp describe(reason), do: inspect(reason)

  @doc "Closes the connection, if any, quietly (the process ends, or starts afresh)."
  @spec close(t) :: t
  def close(%__MODULE__{conn: nil} = c), do: c

  def close(%__MODULE__{conn: conn} = c) do
    Transport.close(conn)
    %{c | conn: nil}
  end

  @doc "The peer answered on this connection: the next wait is the back-off's minimum again."
  @spec alive(t) :: t
  def alive(%__MODULE__{} = c), do: %{c | backoff: Backoff.reset(c.backoff)}

  @doc "Sends bytes on the connection; `{:error, :not_connected}` without one."
  @spec send(t, iodata) :: :ok | {:error, term}
  def send(%__MODULE__{conn: nil}, _bytes), do: {:error, :not_connected}
  def send(%__MODULE__{conn: conn}, bytes), do: Transport.send(conn, bytes)

  @doc "True while a connection is open."
  @spec connected?(t) :: boolean
  def connected?(%__MODULE__{conn: conn}), do: conn != nil

  @doc "The wait `lost/2` or a failed `connect/1` would give now."
  @spec next_wait(t) :: non_neg_integer
  def next_wait(%__MODULE__{backoff: backoff}), do: Backoff.peek(backoff)

  @doc "Takes the back-off's next wait (a driver that waits before dialling of its own accord)."
  @spec wait(t) :: {non_neg_integer, t}
  def wait(%__MODULE__{backoff: backoff} = c) do
    {wait, backoff} = Backoff.next(backoff)
    {wait, %{c | backoff: backoff}}
  end

  defp emit(%__MODULE__{prefix: nil}, _event, _measurements, _metadata), do: :ok

  defp emit(%__MODULE__{} = c, event, measurements, metadata) do
    if event in c.report,
      do:
        Vws.Telemetry.execute(c.prefix ++ [event], measurements, Map.merge(c.metadata, metadata))

    :ok
  end

  ## Option types (`Vws.Options` `{:custom, fun}`), the same in every driver

  @doc false
  def check_endpoint(%Endpoint{} = endpoint), do: {:ok, endpoint}

  def check_endpoint(endpoint) do
    case Endpoint.parse(endpoint) do
      {:ok, _} -> {:ok, endpoint}
      {:error, error} -> {:error, "expected an endpoint (#{Exception.message(error)})"}
    end
  end

  @doc false
  def check_backoff({min, max} = backoff)
      when is_integer(min) and is_integer(max) and min >= 0 and max >= min,
      do: {:ok, backoff}

  def check_backoff(_), do: {:error, "expected {min_ms, max_ms} with 0 <= min <= max"}

  @doc false
  def check_conn(%Transport.Conn{} = conn), do: {:ok, conn}
  def check_conn(_), do: {:error, "expected an open Vws.Links.Transport connection"}

  ## Caller deadlines

  @doc "The deadline `timeout` ms from now (`:infinity` stays)."
  @spec deadline(timeout) :: deadline
  def deadline(:infinity), do: :infinity
  def deadline(timeout) when is_integer(timeout), do: now() + max(timeout, 0)

  @doc "Ms left before `deadline` (0 once it has passed)."
  @spec remaining(deadline) :: timeout
  def remaining(:infinity), do: :infinity
  def remaining(deadline), do: max(deadline - now(), 0)

  @doc "True once `deadline` has passed."
  @spec expired?(deadline) :: boolean
  def expired?(:infinity), do: false
  def expired?(deadline), do: now() >= deadline

  @doc """
  Sends `request` to the driver `server` and waits for its reply until `timeout` (ms or
  `:infinity`) has passed: `{:ok, reply}`, `{:error, :timeout}`, or `{:error, {:exit, reason}}`
  when the driver is not running or ends before it replies. Never exits.
  """
  @spec call(GenServer.server(), term, timeout) ::
          {:ok, term} | {:error, :timeout | {:exit, term}}
  def call(server, request, timeout) do
    {ref, deadline} = send_request(server, request, timeout)
    await(ref, deadline)
  end

  defp await(ref, deadline) do
    receive do
      {[:alias | ^ref], reply} ->
        Process.demonitor(ref, [:flush])
        {:ok, reply}

      {:DOWN, ^ref, _, _, reason} ->
        {:error, {:exit, reason}}
    after
      remaining(deadline) ->
        # the alias goes: a reply sent from now on is dropped; one already here is taken
        Process.demonitor(ref, [:flush])

        receive do
          {[:alias | ^ref], reply} -> {:ok, reply}
        after
          0 -> {:error, :timeout}
        end
    end
  end

  @doc """
  Sends `request` without waiting; the reply comes as a message for `check_response/2`. The
  driver answers by the deadline (`timeout` from now) at the latest.
  """
  @spec send_request(GenServer.server(), term, timeout) :: request_id
  def send_request(server, request, timeout) do
    deadline = deadline(timeout)

    case GenServer.whereis(server) do
      nil ->
        # as a monitor of a process that is not there would say at once
        ref = make_ref()
        Kernel.send(self(), {:DOWN, ref, :process, server, :noproc})
        {ref, deadline}

      pid ->
        # at most one reply reaches the alias; demonitoring ends it too
        ref = :erlang.monitor(:process, pid, alias: :reply_demonitor)
        :gen_statem.cast(pid, {__MODULE__, {self(), [:alias | ref]}, deadline, request})
        {ref, deadline}
    end
  end

  @doc """
  Whether `message` answers `request_id`: `{:ok, reply}`, `{:error, {:exit, reason}}` (the driver
  ended), or `:no_reply` for any other message.
  """
  @spec check_response(term, request_id) :: {:ok, term} | {:error, {:exit, term}} | :no_reply
  def check_response({[:alias | ref], reply}, {ref, _deadline}) do
    Process.demonitor(ref, [:flush])
    {:ok, reply}
  end

  def check_response({:DOWN, ref, _, _, reason}, {ref, _deadline}), do: {:error, {:exit, reason}}
  def check_response(_message, _request_id), do: :no_reply

  @doc """
  The action that turns a request cast by `call/3` or `send_request/3` into the driver's
  event `{:call, from}` with content `{:deadline, deadline, request}`.
  """
  @spec as_call({module, from, deadline, term}) :: {:next_event, {:call, from}, term}
  def as_call({__MODULE__, from, deadline, request}),
    do: {:next_event, {:call, from}, {:deadline, deadline, request}}

  defp now, do: System.monotonic_time(:millisecond)
end
