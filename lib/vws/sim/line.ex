defmodule Vws.Sim.Line do
  @moduledoc """
  A faulty line to put in any link: a relay that listens on one endpoint and, for every
  connection it accepts, dials a target endpoint and carries the bytes both ways, damaging,
  losing, delaying and pacing them as configured.

  Put it where a cable would be. On the WC link SUN_COMM listens and the WC client connects to
  the line instead; on a device link the simulator listens and the CEC's link driver connects to
  the line:

      {:ok, line} = Vws.Sim.Line.start_link(listen: "tcp://127.0.0.1:0",
                                            target: "tcp://127.0.0.1:7070",
                                            seed: 42, faults: [ber: 1.0e-4, baud: 9600])
      {:ok, wc} = Vws.Peers.WC.Client.connect(Vws.Sim.Line.endpoint(line))

  ## Faults, per direction

  The two directions are `:to_target` (from the end that connected to the line towards the
  target) and `:to_client` (back). Each has its own settings, given at start (`:faults` for both,
  then `:to_target` / `:to_client`) and changed at run time with `set_faults/3`, which applies
  to the connections open now and to those to come:

    * `:ber` — each data bit inverted with this probability; `:drop` — each byte lost with this
      probability; `:disconnect_after` — the line is cut once this many bytes have entered it in
      this direction (those bytes still arrive). See `Vws.Sim.Line.Faults`.
    * `:delay`, `:jitter` (ms) — bytes come out `delay` plus a random `0..jitter` ms late, in
      order; `:baud` with `:parity` and `:stop_bits` — bytes come out no faster than a serial line
      of that speed carries them (10 bits a byte for 8N1, 11 with parity); `:disconnect_rate` —
      random cuts, this many per second on average. See `Vws.Sim.Line.Schedule`. A cut in either
      direction cuts the connection.

  A cut (and `disconnect/1`) closes both legs at once, so both ends see their link go down;
  bytes still on the line are lost. When an end closes its connection, the bytes it sent before
  are delivered (paced and delayed as configured) and then the other leg is closed.

  ## Deterministic

  Every direction of every connection draws its faults from its own `:rand` stream, seeded
  from `{seed, n, direction}`, `n` being the connection's number (0, 1, … in accept order). With
  the same seed the same byte sequence comes out with the same damage, however the transport cut
  it into chunks. Timing (delay, jitter, pacing) varies with the machine, as on a real line.

  ## Bounded

  Each direction reads its source active-once and re-arms it only while fewer than `:max_queue`
  bytes (default 64 KiB) wait in it, so a fast sender on a paced line is held back by the
  transport's own flow control, and no buffer grows without bound. (A tty target cannot be held
  back; bytes it sends while the queue is full are lost and counted as `overruns`.)

      iex> {:ok, target} = Vws.Links.Transport.listen("loopback:line-doc-target")
      iex> {:ok, line} = Vws.Sim.Line.start_link(listen: "loopback:line-doc", target: "loopback:line-doc-target",
      ...>                                       faults: [ber: 1.0])
      iex> {:ok, wc} = Vws.Links.Transport.connect(Vws.Sim.Line.endpoint(line))
      iex> {:ok, device} = Vws.Links.Transport.accept(target, 1000)
      iex> :ok = Vws.Links.Transport.send(wc, "A")
      iex> :ok = Vws.Links.Transport.activate(device)
      iex> receive do msg -> Vws.Links.Transport.handle_message(device, msg) end
      {:data, <<0xBE>>}
      iex> Vws.Sim.Line.info(line).to_target.bits_flipped
      8
  """

  use GenServer
  require Logger

  alias Vws.Sim.Line.{Counters, Faults, Schedule, Session}
  alias Vws.Links.Transport

  @type line :: GenServer.server()
  @type direction :: :to_target | :to_client
  # How long set_faults/3 waits for one connection to take new faults.
  @set_faults_wait 1_000
  @fault_keys [:ber, :drop, :disconnect_after] ++
                [:delay, :jitter, :baud, :parity, :stop_bits, :disconnect_rate]

  @doc """
  Starts a line linked to the caller. Options:

    * `:target` (required) — the endpoint each connection is relayed to
    * `:listen` — the endpoint to listen on (default `"tcp://127.0.0.1:0"`, see `endpoint/1`)
    * `:seed` — any term (default 0)
    * `:faults` — settings for both directions; `:to_target`, `:to_client` — for one (applied
      after `:faults`)
    * `:max_queue` — bytes a direction may hold (default 65 536)
    * `:reply_slack` — ms (default 0): on a paced line, bytes the target sends within this time
      after the last bytes it was given came out are its immediate reply, taken to start when
      those bytes were due — the simulated device reacts in no time, as a model; its process's
      own latency is not the line's (`Vws.Sim.GE2000` sets 5)
    * `:connect_timeout` — ms to keep dialling the target for a new connection (default 2 000);
      if it cannot be reached, the accepted connection is closed
    * `:name` — a name to register the line under

  Raises `ArgumentError` on an unknown or out-of-range fault setting.
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    faults = Keyword.get(opts, :faults, [])
    check!(faults)

    per_dir =
      Map.new([:to_target, :to_client], fn dir ->
        dir_opts = Keyword.get(opts, dir, [])
        check!(dir_opts)
        {dir, Keyword.merge(faults, dir_opts)}
      end)

    config = %{
      target: Keyword.fetch!(opts, :target),
      listen: Keyword.get(opts, :listen, "tcp://127.0.0.1:0"),
      seed: Keyword.get(opts, :seed, 0),
      faults: per_dir,
      max_queue: Keyword.get(opts, :max_queue, 65_536),
      reply_slack: Keyword.get(opts, :reply_slack, 0),
      connect_timeout: Keyword.get(opts, :connect_timeout, 2_000)
    }

    GenServer.start_link(__MODULE__, config, Keyword.take(opts, [:name]))
  end

  @doc "The endpoint the line listens on (with the real port when port 0 was asked for)."
  @spec endpoint(line) :: Vws.Links.Endpoint.t()
  def endpoint(line), do: GenServer.call(line, :endpoint)

  @doc """
  Changes the faults of one direction (`:to_target`, `:to_client`) or of `:both`, for open
  connections and new ones; settings not named are kept. Bytes that enter the line after it
  returns meet the new faults (a direction stuck sending to an end that does not read takes them
  when it gets free). Raises `ArgumentError` on an unknown or out-of-range setting.
  """
  @spec set_faults(line, direction | :both, keyword) :: :ok
  def set_faults(line, direction, opts) when direction in [:to_target, :to_client, :both] do
    check!(opts)
    GenServer.call(line, {:set_faults, direction, opts})
  end

  @doc "Cuts every connection now: both ends see their link closed. New connections are relayed."
  @spec disconnect(line) :: :ok
  def disconnect(line), do: GenServer.call(line, :disconnect)

  @doc """
  What the line has done: `%{listening, target, open, faults, connections, disconnects, closes,
  connect_failures, to_target, to_client}`. `open` is the number of connections being relayed,
  `connections` those accepted so far; `disconnects` the cuts made by the line (after N bytes,
  random, or `disconnect/1`), `closes` the connections ended by one of the ends. Each direction
  counts `bytes_in` (entered the line), `bytes_out` (delivered), `bits_flipped` (inverted bits in
  delivered bytes), `bytes_dropped` and `overruns`.
  """
  @spec info(line) :: map
  def info(line), do: GenServer.call(line, :info)

  @doc "Stops the line and every connection through it."
  @spec stop(line) :: :ok
  def stop(line), do: GenServer.stop(line)

  defp check!(opts) do
    unless Keyword.keyword?(opts), do: raise(ArgumentError, "line faults must be a keyword list")

    case Keyword.keys(opts) -- @fault_keys do
      [] -> :ok
      unknown -> raise ArgumentError, "unknown line settings: #{inspect(unknown)}"
    end

    # Both raise ArgumentError on a value out of range.
    Faults.new(opts)
    Schedule.new(opts)
    :ok
  end

  ## Server

  @impl true
  def init(config) do
    Process.flag(:trap_exit, true)

    case Transport.listen(config.listen) do
      {:ok, listener} ->
        me = self()
        acceptor = spawn_link(fn -> accept_loop(listener, me) end)

        {:ok,
         Map.merge(config, %{
           listener: listener,
           listening: Transport.listener_endpoint(listener),
           acceptor: acceptor,
           counters: Counters.new(),
           sessions: %{},
           accepted: 0
         })}

      {:error, reason} ->
        {:stop, {:cannot_listen, config.listen, reason}}
    end
  end

  defp accept_loop(listener, line) do
    case Transport.accept(listener, :infinity) do
      {:ok, conn} ->
        :ok = Transport.controlling_process(conn, line)
        send(line, {:accepted, conn})
        accept_loop(listener, line)

      {:error, _closed} ->
        :ok
    end
  end

  @impl true
  def handle_call(:endpoint, _from, state), do: {:reply, state.listening, state}

  def handle_call({:set_faults, direction, opts}, _from, state) do
    dirs = if direction == :both, do: [:to_target, :to_client], else: [direction]

    state =
      Enum.reduce(dirs, state, fn dir, state ->
        Enum.each(state.sessions, fn {pid, _n} ->
          Session.set_faults(pid, dir, opts, @set_faults_wait)
        end)

        put_in(state.faults[dir], Keyword.merge(state.faults[dir], opts))
      end)

    {:reply, :ok, state}
  end

  def handle_call(:disconnect, _from, state) do
    Enum.each(state.sessions, fn {pid, _n} -> Session.disconnect(pid) end)
    {:reply, :ok, state}
  end

  def handle_call(:info, _from, state) do
    info =
      Map.merge(Counters.read(state.counters), %{
        listening: state.listening,
        target: state.target,
        open: map_size(state.sessions),
        faults: state.faults
      })

    {:reply, info, state}
  end

  @impl true
  def handle_info({:accepted, conn}, state) do
    n = state.accepted

    {:ok, pid} =
      Session.start_link(%{
        target: state.target,
        connect_timeout: state.connect_timeout,
        counters: state.counters,
        max_queue: state.max_queue,
        reply_slack: state.reply_slack,
        faults: state.faults,
        seed: state.seed,
        index: n
      })

    Counters.add(state.counters, :connections)

    case Transport.controlling_process(conn, pid) do
      :ok ->
        Session.begin(pid, conn)

      {:error, _closed} ->
        Transport.close(conn)
        GenServer.stop(pid)
    end

    {:noreply, %{state | accepted: n + 1, sessions: Map.put(state.sessions, pid, n)}}
  end

  def handle_info({:EXIT, pid, reason}, %{acceptor: pid} = state),
    do: {:stop, {:acceptor_down, reason}, state}

  def handle_info({:EXIT, pid, reason}, state) do
    if reason not in [:normal, :shutdown] and Map.has_key?(state.sessions, pid),
      do: Logger.error("line: connection #{state.sessions[pid]} failed: #{inspect(reason)}")

    {:noreply, %{state | sessions: Map.delete(state.sessions, pid)}}
  end

  def handle_info(_msg, state), do: {:noreply, state}

  @impl true
  def terminate(_reason, state) do
    Transport.close_listener(state.listener)

    for {pid, _n} <- state.sessions do
      ref = Process.monitor(pid)
      Process.exit(pid, :shutdown)

      receive do
        {:DOWN, ^ref, _, _, _} -> :ok
      after
        5_000 -> Process.exit(pid, :kill)
      end
    end

    :ok
  end
end
