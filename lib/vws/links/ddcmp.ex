defmodule Vws.Links.DDCMP do
  @moduledoc """
  A DDCMP V4.1 link: the bottom layer of the VAL II supervisory link (PROTOCOLS.md §3, seed
  §4.3.2). It turns a byte transport (`Vws.Links.Transport`) into an ordered, error-free, exactly-once
  stream of messages between two stations, using the codec `Vws.Links.DDCMP.Frame`.

  The protocol itself — the state table below, sequence numbers, what to send, which timer to
  arm — is the pure core `Vws.Links.DDCMP.Protocol`; this module is a process around it that only
  dials, reads, writes and keeps time. A process that owns a wire and speaks the layer above
  runs the core itself, in one process: `Vws.Links.VAL` (the CEC) and `Vws.Sim.VAL2` (the simulated
  controller) do. This link process is for a peer that wants DDCMP alone.

      {:ok, link} = Vws.Links.DDCMP.start_link(endpoint: "tty:/dev/ttyS1?baud=9600", owner: self())
      receive do {:ddcmp, ^link, :up} -> :ok end
      :ok = Vws.Links.DDCMP.send_data(link, <<2, 1, 0, "WHERE">>)
      receive do {:ddcmp, ^link, {:data, message}} -> message end

  Starting a link on a loopback transport, the peer sees our STRT at once (then one DEL fill):

      iex> {:ok, listener} = Vws.Links.Transport.listen("loopback:ddcmp-doc")
      iex> {:ok, link} = Vws.Links.DDCMP.start_link(endpoint: "loopback:ddcmp-doc", owner: self())
      iex> {:ok, peer} = Vws.Links.Transport.accept(listener, 5000)
      iex> Vws.Links.Transport.activate(peer)
      iex> receive do msg -> Vws.Links.Transport.handle_message(peer, msg) end
      {:data, <<0x05, 0x06, 0xC0, 0x00, 0x00, 0x01, 0x75, 0x95, 0xFF>>}
      iex> Vws.Links.DDCMP.info(link).state
      :istrt
      iex> Vws.Links.DDCMP.stop(link)
      :ok

  ## Connecting

  Give exactly one of:

    * `endpoint: "tcp://host:port" | "tty:/dev/x?baud=9600" | "loopback:name"` — the link dials
      the endpoint itself (never in `init/1`) and dials again, with exponential backoff
      (`:backoff`, default `{100, 5000}` ms), whenever the peer goes away. Use this under a
      supervisor.
    * `conn: conn` — an already connected `Vws.Links.Transport` connection, e.g. one a simulator
      accepted. `start_link/1` hands it over to the link itself, so it must be called by the
      connection's controlling process, before that process ever called `Vws.Links.Transport.activate/1`
      on it. When that connection closes the owner gets `{:down, :closed}` and the link process
      exits normally.

  ## Owner messages

  The owner (option `:owner`, a pid or registered name; default the caller of `start_link/1`)
  receives, with `link` the link's pid:

    * `{:ddcmp, link, :up}` — start-up completed, the link is RUNNING;
    * `{:ddcmp, link, {:data, binary}}` — a data message from the peer, in order, each once;
    * `{:ddcmp, link, {:down, reason}}` — the link left RUNNING: `:too_many_failures`,
      `:restart` (after `restart/1`), `:maintenance`, `:closed` or `{:transport, reason}`;
    * `{:ddcmp, link, :peer_restarted}` — a STRT arrived while RUNNING: the peer restarted.

  `:up` alternates with `{:down, _}` / `:peer_restarted`. Each time the link enters RUNNING a new
  **session** begins (numbered 1, 2, … in `info/1`). An owner that must never answer a message
  of one session in the next runs the protocol core in its own process instead, as
  `Vws.Links.VAL` does: this process API is for tests and tools. Whenever the link leaves RUNNING the
  messages not yet acknowledged by the peer, and those still queued, are dropped: the layer above
  decides what to send again. Messages given to `send_data/2` while the link is not RUNNING wait
  for it (in order) and go out once it is.

  ## Options

    * `:window` — most data messages outstanding (sent, not acknowledged), 1..255, default 7;
    * `:rep_timeout` — the reply timer, ms, default 3000: while messages are outstanding and
      nothing acknowledges them, REP(N) is sent this often;
    * `:start_timeout` — STRT/STACK resend interval during start-up, ms, default 3000;
    * `:max_failures` — successive REP timeouts or NAKs (other than the answer to our REP) after
      which the link is declared down and restarted, default 8 (as Adept V+);
    * `:role` — `:active` sends STRT when the transport is up (the CEC); `:passive` waits for the
      peer's STRT (a simulated VAL II), default `:active`;
    * `:max_data` — longest data message sent or received, bytes, default 4096 (at most 16383);
      longer received messages are NAKed (reason 16);
    * `:name` — registers the link (`atom`, `{:global, term}` or `{:via, module, term}`);
    * `:workstation` — the id of the workstation the link serves, for telemetry metadata;
    * `:id` — the child spec's id (`child_spec/1`).

  Checked by `start_link/1` (`Vws.Options`): an unknown option or a bad value raises
  `Vws.Options.Error` naming it.
    * `:backoff` — `{min, max}` reconnect delay for `:endpoint`, ms, doubling with every wait and
      back to `min` only once the link has run (`Vws.Links.Backoff`): a peer that accepts and drops
      the connection before start-up completes is dialled less and less often.

  ## States (DDCMP V4.1 §5)

  Variables, mod 256: R = highest message received in sequence, N = highest sent, A = highest
  acknowledged by the peer, T = next to (re)transmit. Every frame we send is followed by one DEL.

  | state | event | action | next |
  |-------|-------|--------|------|
  | HALTED | transport up (`:endpoint` connected / `:conn` handed over) | reset; `:active`: send STRT, start timer | ISTRT |
  | HALTED | `restart/1` with a transport | reset; send STRT, start timer | ISTRT |
  | HALTED | any frame | ignore | HALTED |
  | ISTRT | receive STRT | send STACK, start timer | ASTRT |
  | ISTRT | receive STACK | send ACK(0), stop timer, owner `:up` | RUNNING |
  | ISTRT | timer expires | reset; send STRT, start timer | ISTRT |
  | ISTRT | receive ACK, NAK, REP, data, error | ignore | ISTRT |
  | ASTRT | receive STACK | send ACK(0), stop timer, owner `:up` | RUNNING |
  | ASTRT | receive ACK with RESP = 0 | stop timer, owner `:up` | RUNNING |
  | ASTRT | receive data with RESP = 0 | stop timer, owner `:up`, process it as in RUNNING | RUNNING |
  | ASTRT | receive STRT | send STACK, start timer | ASTRT |
  | ASTRT | timer expires | send STACK, start timer | ASTRT |
  | ASTRT | receive other ACK, NAK, REP, data, error | ignore | ASTRT |
  | ISTRT / ASTRT → RUNNING | (entering RUNNING) | session := session + 1 | RUNNING |
  | RUNNING | `send_data/2` | queue; sent when T = N + 1 and N − A < window, with RESP = R | RUNNING |
  | RUNNING | receive data, NUM = R + 1 | R := NUM, give to owner, set SACK | RUNNING |
  | RUNNING | receive data, other NUM | discard | RUNNING |
  | RUNNING | receive data or ACK, A < RESP ≤ N | A := RESP (messages up to it done), T := max(T, A + 1); all done → stop timer | RUNNING |
  | RUNNING | receive data or ACK, RESP outside A < RESP ≤ N | ignore the RESP | RUNNING |
  | RUNNING | receive NAK, A ≤ RESP ≤ N | A := RESP, T := A + 1 (retransmit the rest), stop timer | RUNNING |
  | RUNNING | receive NAK, RESP outside A ≤ RESP ≤ N | ignore | RUNNING |
  | RUNNING | receive REP, NUM = R | set SACK (send ACK(R)) | RUNNING |
  | RUNNING | receive REP, NUM ≠ R | set SNAK reason 3 | RUNNING |
  | RUNNING | receive STACK | set SACK | RUNNING |
  | RUNNING | header CRC / data CRC / too long / header format error | set SNAK reason 1 / 2 / 16 / 17 (data CRC and too long: still take RESP) | RUNNING |
  | RUNNING | reply timer expires | set SREP (send REP(N)), start timer | RUNNING |
  | RUNNING | `max_failures` successive timeouts / NAKs | owner `{:down, :too_many_failures}`, drop queue; reset; `:active`: send STRT | ISTRT |
  | RUNNING | receive STRT | owner `:peer_restarted`, drop queue; reset; `:active`: send STRT, `:passive`: answer it (STACK) | ISTRT / ASTRT |
  | RUNNING | `restart/1` | owner `{:down, :restart}`, drop queue; reset; send STRT | ISTRT |
  | any | receive maintenance message | owner `{:down, :maintenance}` if RUNNING | HALTED |
  | any | transport closed | owner `{:down, :closed}` if RUNNING; `:endpoint`: dial again | HALTED |

  Sending in RUNNING follows the spec's priority after each request or received chunk: NAK
  (SNAK), then REP (SREP), then retransmissions T..N, then new messages, then a lone ACK(R) if
  SACK is still set (any data message carries RESP = R and clears SACK). The reply timer is
  (re)started whenever a data message or REP goes out while messages are outstanding. A STRT in
  RUNNING halts the link in the spec; this link then restarts at once ("user startup").
  `start_timeout` resends go on for ever: only the peer can end start-up.

  ## Telemetry

  `[:vws, :ddcmp, event]`, metadata always with `link` (the `:name`, else the pid) and
  `workstation` (the `:workstation` option, nil without):

  | event | measurements | metadata |
  |-------|--------------|----------|
  | `:frame_sent` / `:frame_received` | `count` | `type` and `num, resp, bytes` (data) or `subtype, rcvr, sndr` (control) |
  | `:nak` | `count` | `direction` (`:sent`/`:received`), `reason`, `resp` |
  | `:rep` | `count` | `direction`, `num` |
  | `:retransmission` | `count, bytes` | `num` |
  | `:receive_error` | `count` | `reason`, `num` |
  | `:state_change` | `count` | `from, to` |
  | `:link_down` | `count` | `reason` |
  | `:connect_failed` | `count`, `retry_in` (ms to the next attempt) | `endpoint`, `reason` (`:endpoint` links) |
  """

  alias Vws.Links.DDCMP.Link

  @type link :: :gen_statem.server_ref()

  @type option ::
          {:endpoint, String.t() | Vws.Links.Endpoint.t()}
          | {:conn, Vws.Links.Transport.Conn.t()}
          | {:owner, pid | atom | {:global, term} | {:via, module, term}}
          | {:name, atom | {:global, term} | {:via, module, term}}
          | {:window, 1..255}
          | {:rep_timeout, pos_integer}
          | {:start_timeout, pos_integer}
          | {:max_failures, pos_integer}
          | {:role, :active | :passive}
          | {:max_data, 0..16383}
          | {:backoff, {pos_integer, pos_integer}}
          | {:id, term}
          | {:workstation, term}

  # the protocol's options (`Vws.Links.DDCMP.Protocol`), also those of a process that runs the
  # core itself (`Vws.Links.VAL`, `Vws.Sim.VAL2`)
  defp protocol_schema do
    [
      window: [type: {:in, 1..255}, default: 7],
      rep_timeout: [type: :pos_integer, default: 3000],
      start_timeout: [type: :pos_integer, default: 3000],
      max_failures: [type: :pos_integer, default: 8],
      role: [type: {:in, [:active, :passive]}, default: :active],
      max_data: [type: {:in, 0..16383}, default: 4096],
      backoff: [type: {:custom, &Vws.Links.Connection.check_backoff/1}, default: {100, 5000}],
      workstation: [type: :any]
    ]
  end

  # (functions, not attributes: a captured function in an attribute is a compile-time dependency)
  defp schema do
    [
      endpoint: [type: {:custom, &Vws.Links.Connection.check_endpoint/1}],
      conn: [type: {:custom, &Vws.Links.Connection.check_conn/1}],
      owner: [type: :any],
      name: [type: :any],
      id: [type: :any]
    ] ++ protocol_schema()
  end

  @doc """
  A child spec (`:id` defaults to `:name`, else `Vws.Links.DDCMP`). Under a supervisor use `:endpoint`
  and an explicit `:owner`.
  """
  @spec child_spec([option]) :: Supervisor.child_spec()
  def child_spec(opts) do
    %{
      id: Keyword.get_lazy(opts, :id, fn -> Keyword.get(opts, :name, __MODULE__) end),
      start: {__MODULE__, :start_link, [opts]},
      type: :worker
    }
  end

  @doc """
  Starts a link linked to the caller (see the moduledoc for the options). Returns once the link
  runs; start-up with the peer goes on in the background and ends with `{:ddcmp, link, :up}`.
  Raises `ArgumentError` for invalid options.
  """
  @spec start_link([option]) :: :gen_statem.start_ret()
  def start_link(opts) do
    opts = validate!(opts)
    {conn, opts} = Keyword.pop(opts, :conn)

    start =
      case Keyword.fetch(opts, :name) do
        {:ok, name} when is_atom(name) -> :gen_statem.start_link({:local, name}, Link, opts, [])
        {:ok, name} -> :gen_statem.start_link(name, Link, opts, [])
        :error -> :gen_statem.start_link(Link, opts, [])
      end

    with {:ok, pid} <- start, true <- conn != nil do
      attach(pid, conn)
    else
      false -> start
      error -> error
    end
  end

  defp attach(pid, conn) do
    case Vws.Links.Transport.controlling_process(conn, pid) do
      :ok ->
        :ok = :gen_statem.call(pid, {:attach, conn})
        {:ok, pid}

      {:error, reason} ->
        :gen_statem.stop(pid)
        {:error, reason}
    end
  end

  @doc """
  Queues a data message for the peer. `:ok` once queued; it is sent within the transmit window and
  retransmitted until acknowledged. Before the link is RUNNING the message waits for it.
  `{:error, :too_long}` if it is longer than `:max_data`.

  With `hold: false` a message is refused with `{:error, :not_running}` unless the link is RUNNING:
  a command meant for this session must never be delivered in the next one (after a restart).
  A link process that has ended refuses it the same way.
  """
  @spec send_data(link, iodata, keyword) :: :ok | {:error, :too_long | :not_running}
  def send_data(link, iodata, opts \\ []) do
    [hold: hold] =
      Vws.Options.validate!(opts, [hold: [type: :boolean, default: true]], "send_data")

    request = {:send, IO.iodata_to_binary(iodata), hold: hold}

    case Vws.Links.Connection.call(link, request, :infinity) do
      {:ok, reply} ->
        reply

      # A link that has ended is RUNNING in no session: the refusal the caller is ready for, not
      # an exit. Its owner traps exits, and the link's end may still wait in the owner's mailbox
      # behind the message it is answering (a peer whose connection just died).
      {:error, {:exit, _reason}} when hold == false ->
        {:error, :not_running}

      {:error, {:exit, reason}} ->
        exit({reason, {__MODULE__, :send_data, [link]}})
    end
  end

  @doc """
  Re-initialises the link (the seed's STRT between robot commands): sends STRT and goes back
  through start-up; `{:down, :restart}` if it was RUNNING, then `:up` again once the peer answers.
  Unacknowledged and queued messages are dropped. A link halted by a maintenance message starts
  again this way; one whose transport is down starts by itself once it is back.
  """
  @spec restart(link) :: :ok
  def restart(link), do: :gen_statem.call(link, :restart)

  @doc """
  The link's state and numbers: `state`, `role`, `connected`, `peer`, `session` (the number of
  the latest session, 0 before the first), `r`, `n`, `a`, `t`,
  `window`, `outstanding`, `queue` (waiting for the window), `failures` (successive),
  `counters` (`sent, received, retransmitted, naks_sent, naks_received, reps_sent, timeouts,
  header_crc_errors, data_crc_errors, restarts, ignored, unexpected`), `halt_reason` (HALTED only)
  and `last_error`.
  """
  @spec info(link) :: map
  def info(link), do: :gen_statem.call(link, :info)

  @doc "Stops the link and closes its transport."
  @spec stop(link, term, timeout) :: :ok
  def stop(link, reason \\ :normal, timeout \\ :infinity),
    do: :gen_statem.stop(link, reason, timeout)

  @doc false
  # The options checked once, by the caller, with the defaults filled in (also `Vws.Links.VAL`'s).
  def validate!(opts) do
    opts = Vws.Options.validate!(opts, schema(), "DDCMP")

    case {Keyword.has_key?(opts, :endpoint), Keyword.has_key?(opts, :conn)} do
      {true, false} -> :ok
      {false, true} -> :ok
      _ -> raise ArgumentError, "Vws.Links.DDCMP needs exactly one of :endpoint or :conn"
    end

    Keyword.put_new(opts, :owner, self())
  end

  @doc false
  # The protocol's options alone, for a process that brings its own transport (`Vws.Sim.VAL2`).
  def validate_protocol!(opts), do: Vws.Options.validate!(opts, protocol_schema(), "DDCMP")
end
