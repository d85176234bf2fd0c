defmodule Vws.Sim.VAL2 do
  @moduledoc """
  A simulated Unimation VAL II robot controller on its own endpoint: the supervisory port of
  seed §4.3 — DDCMP (`Vws.Links.DDCMP.Protocol`, role `:passive`, run by this process itself: one
  process per wire) carrying VAL data messages (`Vws.Links.VAL.Message`) — in front of a simulated arm (`Vws.Sim.VAL2.Monitor`,
  `Vws.Sim.VAL2.Kinematics`) with the named locations of `priv/sims/robot_locations.exs`.

      {:ok, sim} = Vws.Sim.VAL2.start_link(time_scale: 0.01)
      endpoint = Vws.Sim.VAL2.endpoint(sim)      # "tcp://127.0.0.1:40123"
      {:ok, val} = Vws.Links.VAL.start_link(ddcmp: [endpoint: endpoint])
      :ok = Vws.Links.VAL.motion(val, "DO MOVE VISE", 10_000)

  ## The supervisory system, as simulated

  On every start-up of the link LUN 2 prompts (a READ with text `.`), and LUN 1 sends the short
  status. A monitor command arrives as the CEC's LUN 2 WRITE answering the prompt; the monitor
  answers with a LUN 2 WRITE, `0` plus any output or a negative error number and its text (the
  table in `Vws.Sim.VAL2.Monitor`), and prompts again once the CEC has replied. A `DO` that is
  accepted answers `0` at once; LUN 3 then sends MOTION BEGIN, and MOTION COMPLETE when the arm
  arrives — after the time the move takes (`Vws.Sim.VAL2.Monitor`) times `:time_scale`. An
  `EXECUTE` sends PROGRAM START, runs the program's motions, then PROGRAM COMPLETE; a step that
  fails sends a LUN 3 ERROR and ends the program.

  Each logical unit obeys the rule of seed §4.3.3: it sends its next message only after the CEC's
  reply to the previous one (a READ is answered by the CEC's WRITE, a WRITE by a REPLY), while
  the other units go on. Anything the CEC does against the rules — a command without a prompt, a
  reply nothing waits for, a READ (VAL II initiates everything) — is not obeyed: it is logged and
  counted in `info/1` as a `violation`, so tests can check the CEC side never breaks a rule.

  On LUNs 1 and 2 each message a unit initiates is numbered in its qualifier, and an answer
  must carry the number of what it answers (`Vws.Links.VAL`, "Numbers"). An answer with a number
  this session of the link never used is left over from before a restart (a CEC that gave it to
  its link as the link was starting again): it is not obeyed, and counted as `stale`, not as a
  violation.

  A new connection takes over from the previous one, as a new cable would.

  ## The plant

  `on_move` (option) is called with `%{volume, location, phase, world}` when a motion begins
  (`phase: :begin`, `volume` the work volume of the target, unless the target is `:safe`, which
  counts only on arrival) and when it ends (`:complete`, or `:stopped` when a fault or restart
  stopped the arm). Volumes are those of the locations file (`:tray1`, `:tray2`, `:vise`,
  `:table`, else `:safe`), the plant simulator's names. The map carries `carrying: boolean`
  only when the simulator has been told (`set_carrying/2` or option `:carrying`), since the
  plant, not the robot, knows where the parts are.

  ## Options

    * `:endpoint` — where to listen (default `"tcp://127.0.0.1:0"`, any free port); an endpoint
      that cannot listen (a tty) is opened directly
    * `:allow` — who may connect (`Vws.Links.Transport.Policy`; default loopback only)
    * `:locations` — a locations file path, or its map (default `priv/sims/robot_locations.exs`)
    * `:time_scale` — multiplies every motion time (default 1.0; tests use ~0.001)
    * `:on_move` — `fun(map)`, see "The plant"
    * `:carrying` — the initial payload flag (`nil`: not reported)
    * `:ddcmp` — further `Vws.Links.DDCMP` options (`:rep_timeout`, `:window`, `:backoff` for a tty, …)
    * `:name` — registered name
  """
  use GenServer
  require Logger

  alias Vws.Links.DDCMP.{Protocol, Wire}
  alias Vws.Sim.VAL2.Monitor
  alias Vws.Links.Transport
  alias Vws.Links.VAL.Message

  @lun_short_status 1
  @lun_monitor 2
  @lun_async 3
  @prompt "."

  @doc false
  def child_spec(opts) do
    %{id: Keyword.get(opts, :id, __MODULE__), start: {__MODULE__, :start_link, [opts]}}
  end

  @doc "Starts a simulated controller (see the module doc for options)."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts \\ []) do
    case Keyword.get(opts, :name) do
      nil -> GenServer.start_link(__MODULE__, opts)
      name -> GenServer.start_link(__MODULE__, opts, name: name)
    end
  end

  @doc "The endpoint the controller listens on, as a string (its real port when `:0` was asked)."
  @spec endpoint(GenServer.server()) :: String.t()
  def endpoint(sim), do: GenServer.call(sim, :endpoint)

  @doc """
  The controller's state: `location` (name of the location it is at, `nil` between names),
  `world`, `joints`, `volume`, `speed`, `moving`, `program`, `link` (up?), `line` (the DDCMP
  protocol's state and numbers, `Vws.Links.DDCMP.Protocol.info/1`; nil before a connection), `commands` (every
  monitor command obeyed, in order), `violations` (CEC rule breaks), `stale` (answers left over
  from an earlier session, not obeyed), `restarts`.
  """
  @spec info(GenServer.server()) :: map
  def info(sim), do: GenServer.call(sim, :info)

  @doc """
  Simulates a controller restart: the arm stops where it is, the monitor forgets the command and
  program in hand, speed returns to its default, and the link starts up again (the CEC's link
  sees a STRT while running: its peer restarted).
  """
  @spec restart(GenServer.server()) :: :ok
  def restart(sim), do: GenServer.call(sim, :restart)

  @doc "Tells the simulator whether the gripper holds a part (`nil`: unknown, not reported)."
  @spec set_carrying(GenServer.server(), boolean | nil) :: :ok
  def set_carrying(sim, carrying), do: GenServer.call(sim, {:set_carrying, carrying})

  @doc """
  Makes the next motion fail half-way with a hardware error: the arm stops and LUN 3 sends
  ERROR with `"<code> <text>"`.
  """
  @spec fault(GenServer.server(), integer, String.t()) :: :ok
  def fault(sim, code, text), do: GenServer.call(sim, {:fault, {code, text}})

  @doc "Stops the simulator."
  @spec stop(GenServer.server()) :: :ok
  def stop(sim), do: GenServer.stop(sim)

  ## Server

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)

    config =
      case Keyword.get(opts, :locations) do
        %{} = map -> map
        path -> Monitor.load_config(path)
      end

    state = %{
      monitor: Monitor.new(config),
      endpoint: Keyword.get(opts, :endpoint, "tcp://127.0.0.1:0"),
      allow: Vws.Links.Transport.Policy.parse_allow!(Keyword.get(opts, :allow)),
      bound: nil,
      listener: nil,
      acceptor: nil,
      # the wire: a connection, the DDCMP protocol on it and its armed timers
      conn: nil,
      protocol: nil,
      timers: %{},
      backoff: nil,
      up: false,
      ddcmp: Vws.Links.DDCMP.validate_protocol!(Keyword.get(opts, :ddcmp, [])),
      # false while a chunk's news is handled: the units send once it all is
      pumping: true,
      time_scale: Keyword.get(opts, :time_scale, 1.0),
      on_move: Keyword.get(opts, :on_move),
      carrying: Keyword.get(opts, :carrying),
      # per LUN: what the unit waits for from the CEC (nil, :reply or :input) and its queue
      waiting: %{},
      outbox: %{},
      # per LUN: the numbers (LUN 3: the codes) sent in this session of the link
      session: %{},
      numbers: %{},
      stale: 0,
      motion: nil,
      fault: nil,
      commands: [],
      workstation: Vws.Names.id_of(Keyword.get(opts, :name)),
      violations: 0,
      restarts: 0
    }

    {:ok, state, {:continue, :open}}
  end

  @impl true
  def handle_continue(:open, s) do
    case Transport.listen(s.endpoint) do
      {:ok, listener} ->
        bound = to_string(Transport.listener_endpoint(listener))
        owner = self()
        acceptor = Transport.start_acceptor(listener, owner, :accepted, allow: s.allow)
        Logger.info("VAL II simulator listening on #{bound}")
        {:noreply, %{s | listener: listener, bound: bound, acceptor: acceptor}}

      {:error, %Transport.Error{reason: :not_listenable}} ->
        # a tty: opened here, and opened again (with back-off) whenever it goes away
        {min, max} = Keyword.fetch!(s.ddcmp, :backoff)
        s = %{s | bound: to_string(s.endpoint), backoff: Vws.Links.Backoff.new(min, max)}
        {:noreply, dial(s)}

      {:error, reason} ->
        {:stop, {:listen_failed, reason}, s}
    end
  end

  @impl true
  def handle_call(:endpoint, _from, s), do: {:reply, s.bound, s}

  def handle_call(:info, _from, s) do
    m = s.monitor
    {world, joints} = Monitor.coordinates(m, nil)

    info = %{
      location: m.location,
      world: world,
      joints: joints,
      volume: Monitor.volume(m, nil),
      speed: m.speed,
      moving: m.motion != nil,
      program: m.program && m.program.name,
      link: s.up,
      line: s.protocol && Protocol.info(s.protocol),
      commands: Enum.reverse(s.commands),
      violations: s.violations,
      stale: s.stale,
      restarts: s.restarts,
      carrying: s.carrying
    }

    {:reply, info, s}
  end

  def handle_call(:restart, _from, s) do
    Logger.warning("VAL II simulator: controller restart")
    stopped = s.monitor.motion != nil
    s = %{s | monitor: Monitor.restart(s.monitor, fraction(s)), motion: nil, fault: nil}
    if stopped, do: notify(s, :stopped)
    s = %{s | waiting: %{}, outbox: %{}, restarts: s.restarts + 1, up: false}
    s = if s.protocol, do: line(s, Protocol.restart(s.protocol)), else: s
    {:reply, :ok, s}
  end

  def handle_call({:set_carrying, carrying}, _from, s),
    do: {:reply, :ok, %{s | carrying: carrying}}

  def handle_call({:fault, fault}, _from, s), do: {:reply, :ok, %{s | fault: fault}}

  @impl true
  def handle_info({:accepted, conn}, s) do
    s =
      if s.conn do
        Logger.info("VAL II simulator: a new connection takes over")
        Transport.close(s.conn)
        line(%{s | conn: nil}, Protocol.disconnected(s.protocol, :taken_over))
      else
        s
      end

    :ok = Transport.activate(conn)
    {:noreply, connected(s, conn)}
  end

  def handle_info(:dial, s), do: {:noreply, dial(s)}

  def handle_info({:timeout, ref, {:ddcmp, timer}}, s) do
    if s.timers[timer] == ref do
      s = %{s | timers: Map.delete(s.timers, timer)}
      {:noreply, line(s, Protocol.handle_timeout(s.protocol, timer))}
    else
      {:noreply, s}
    end
  end

  def handle_info({:motion_done, ref}, %{motion: %{ref: ref}} = s) do
    s = %{s | monitor: Monitor.complete_motion(s.monitor), motion: nil}
    notify(s, :complete)

    if s.monitor.program do
      {:noreply, next_program_step(s)}
    else
      {:noreply,
       s |> enqueue(@lun_async, {:write, :motion_complete, "MOTION COMPLETE"}) |> pump_all()}
    end
  end

  def handle_info({:motion_fault, ref, {code, text}}, %{motion: %{ref: ref}} = s) do
    s = %{s | monitor: Monitor.stop_motion(s.monitor, 0.5), motion: nil}
    notify(s, :stopped)
    {:noreply, s |> enqueue(@lun_async, {:write, :error, "#{code} #{text}"}) |> pump_all()}
  end

  def handle_info(message, %{conn: conn} = s) when conn != nil do
    case Transport.handle_message(conn, message) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        {:noreply, line(s, Protocol.handle_bytes(s.protocol, bytes))}

      :closed ->
        {:noreply, disconnected(s, :closed)}

      {:error, reason} ->
        {:noreply, disconnected(s, {:transport, reason})}

      :unknown ->
        other_info(message, s)
    end
  end

  def handle_info(message, s), do: other_info(message, s)

  # The wire -------------------------------------------------------------------------------------

  # A fresh protocol on every connection, as a controller's port after a new cable.
  defp connected(s, conn) do
    protocol = Protocol.new(Keyword.put(s.ddcmp, :role, :passive))
    s = %{s | conn: conn, protocol: protocol, up: false, waiting: %{}}
    line(s, Protocol.connect(protocol))
  end

  defp dial(s) do
    case Transport.connect(s.endpoint) do
      {:ok, conn} ->
        :ok = Transport.activate(conn)
        connected(s, conn)

      {:error, reason} ->
        {delay, backoff} = Vws.Links.Backoff.next(s.backoff)
        Logger.info("VAL II simulator: cannot open #{s.bound} (#{inspect(reason)})")
        Process.send_after(self(), :dial, delay)
        %{s | backoff: backoff}
    end
  end

  defp disconnected(s, reason) do
    Logger.info("VAL II simulator: connection ended (#{inspect(reason)})")
    Transport.close(s.conn)
    s = line(%{s | conn: nil}, Protocol.disconnected(s.protocol, reason))

    if s.backoff do
      {delay, backoff} = Vws.Links.Backoff.next(s.backoff)
      Process.send_after(self(), :dial, delay)
      %{s | backoff: backoff}
    else
      s
    end
  end

  # A result of the protocol: frames out, timers armed, news handled in order; then the units
  # send what may go now.
  defp line(s, {protocol, frames, events}) do
    meta = %{link: self(), workstation: s.workstation}
    {news, timers} = Wire.perform_raw(frames, events, s.conn, meta)
    s = %{s | protocol: protocol, timers: Wire.arm(s.timers, timers)}
    pumping = s.pumping
    s = Enum.reduce(news, %{s | pumping: false}, &news/2)
    s = %{s | pumping: pumping}
    if pumping and news != [], do: pump_all(s), else: s
  end

  defp news(:up, s) do
    # every start-up: the units start afresh, LUN 2 prompts, LUN 1 tells its status
    s = if s.backoff, do: %{s | backoff: Vws.Links.Backoff.reset(s.backoff)}, else: s
    s = %{s | up: true, waiting: %{}, session: %{}, outbox: Map.delete(s.outbox, @lun_monitor)}
    s |> enqueue(@lun_monitor, {:read, 0, @prompt}) |> enqueue_status()
  end

  defp news({:down, reason}, s) do
    Logger.info("VAL II simulator: link down (#{inspect(reason)})")
    %{s | up: false, waiting: %{}}
  end

  defp news(:peer_restarted, s) do
    Logger.info("VAL II simulator: the CEC restarted the link")
    %{s | up: false, waiting: %{}}
  end

  # data after the link's end in the same chunk: from a session that has ended, not obeyed
  defp news({:data, _bytes}, %{up: false} = s), do: %{s | stale: s.stale + 1}

  defp news({:data, bytes}, s) do
    case Message.decode(bytes) do
      {:ok, m} ->
        receive_message(m, s)

      {:error, e} ->
        Logger.warning("VAL II simulator: bad VAL message: #{Exception.message(e)}")
        violation(s)
    end
  end

  defp other_info({:EXIT, acceptor, reason}, %{acceptor: acceptor} = s), do: {:stop, reason, s}
  defp other_info({:EXIT, _pid, :normal}, s), do: {:noreply, s}
  defp other_info({:EXIT, _pid, reason}, s), do: {:stop, reason, s}

  defp other_info(msg, s) do
    Logger.debug("VAL II simulator: ignored #{inspect(msg, limit: 5)}")
    {:noreply, s}
  end

  @impl true
  def terminate(_reason, s) do
    if s.listener, do: Transport.close_listener(s.listener)
    if s.conn, do: Transport.close(s.conn)
    :ok
  end

  ## The logical units

  defp receive_message(%Message{lun: lun, function: :reply, qualifier: q}, s) do
    case s.waiting[lun] do
      {:reply, ^q} ->
        pump(%{s | waiting: Map.put(s.waiting, lun, nil)}, lun)

      _ ->
        unanswered(s, lun, q, "REPLY on LUN #{lun} (#{inspect(q)}) that nothing waits for")
    end
  end

  defp receive_message(%Message{lun: @lun_monitor, function: :write, qualifier: q} = m, s) do
    case s.waiting[@lun_monitor] do
      {:input, ^q} ->
        s = %{s | waiting: Map.put(s.waiting, @lun_monitor, nil), commands: [m.text | s.commands]}

        Vws.Telemetry.execute([:vws, :sim, :val2, :command], %{count: 1}, %{
          workstation: s.workstation,
          text: m.text
        })

        monitor_command(s, m.text)

      _ ->
        unanswered(s, @lun_monitor, q, "command #{inspect(m.text)} (#{q}) without its prompt")
    end
  end

  defp receive_message(%Message{} = m, s) do
    Logger.warning(
      "VAL II simulator: #{m.function} on LUN #{m.lun} from the CEC breaks the protocol"
    )

    violation(s)
  end

  defp monitor_command(s, text) do
    {reply, effects, monitor} = Monitor.command(s.monitor, text)
    s = %{s | monitor: monitor}

    response =
      case reply do
        {:ok, ""} -> "0"
        {:ok, output} -> "0\r\n" <> output
        {:error, code, message} -> "#{code} #{message}"
      end

    s =
      s
      |> enqueue(@lun_monitor, {:write, 0, response})
      |> enqueue(@lun_monitor, {:read, 0, @prompt})

    s =
      Enum.reduce(effects, s, fn
        {:motion, plan}, s ->
          s |> enqueue(@lun_async, {:write, :motion_begin, "MOTION BEGIN"}) |> start_motion(plan)

        {:program, name}, s ->
          s
          |> enqueue(@lun_async, {:write, :program_start, "PROGRAM START " <> name})
          |> next_program_step()
      end)

    s |> enqueue_status() |> pump_all()
  end

  defp next_program_step(s) do
    name = s.monitor.program.name

    case Monitor.next_step(s.monitor) do
      {:motion, plan, monitor} ->
        start_motion(%{s | monitor: monitor}, plan)

      {:error, code, text, monitor} ->
        enqueue(%{s | monitor: monitor}, @lun_async, {:write, :error, "#{code} #{text}"})
        |> pump_all()

      {:done, monitor} ->
        %{s | monitor: monitor}
        |> enqueue(@lun_async, {:write, :program_complete, "PROGRAM COMPLETE " <> name})
        |> enqueue_status()
        |> pump_all()
    end
  end

  defp start_motion(s, plan) do
    ref = make_ref()
    ms = round(plan.duration_ms * s.time_scale)

    {s, message} =
      case s.fault do
        nil -> {s, {:motion_done, ref}}
        fault -> {%{s | fault: nil}, {:motion_fault, ref, fault}}
      end

    ms = if elem(message, 0) == :motion_fault, do: div(ms, 2), else: ms
    Process.send_after(self(), message, ms)
    s = %{s | motion: %{ref: ref, started: now(), ms: max(ms, 1), plan: plan}}
    notify(s, :begin)
    s
  end

  defp fraction(%{motion: nil}), do: 0.0
  defp fraction(%{motion: %{started: t0, ms: ms}}), do: min((now() - t0) / ms, 1.0)

  defp notify(%{on_move: nil}, _phase), do: :ok

  defp notify(s, phase) do
    m = s.monitor
    config = m.config

    {volume, location, world} =
      case {phase, s.motion} do
        {:begin, %{plan: plan}} ->
          target = Monitor.volume(plan.to, config)
          volume = if target == :safe, do: Monitor.volume(plan.from, config), else: target
          {world, _} = Monitor.coordinates(plan.to, config.arm)
          {volume, plan.target, world}

        _ ->
          {world, _} = Monitor.coordinates(m, nil)
          {Monitor.volume(m, nil), m.location, world}
      end

    event = %{volume: volume, location: location, phase: phase, world: world}
    event = if s.carrying == nil, do: event, else: Map.put(event, :carrying, s.carrying)

    try do
      s.on_move.(event)
    catch
      kind, reason ->
        Logger.warning("VAL II simulator: on_move failed: #{inspect({kind, reason})}")
    end

    :ok
  end

  defp short_status(s) do
    m = s.monitor
    state = if m.program, do: "PROGRAM " <> m.program.name, else: "MONITOR"

    "#{state} SPEED #{:erlang.float_to_binary(m.speed, decimals: 1)} " <>
      if(m.motion, do: "MOVING", else: "STOPPED")
  end

  # the short status not yet sent is replaced by the latest: LUN 1 tells the present, not history
  defp enqueue_status(s) do
    %{s | outbox: Map.put(s.outbox, @lun_short_status, [{:write, 0, short_status(s)}])}
  end

  defp enqueue(s, lun, message) do
    %{s | outbox: Map.update(s.outbox, lun, [message], &(&1 ++ [message]))}
  end

  defp pump_all(s), do: Enum.reduce(Map.keys(s.outbox), s, &pump(&2, &1))

  # Sends the unit's next message if it is not waiting for the CEC and the link is up. While a
  # chunk's news is handled nothing is sent (`pumping: false`): what the chunk's data causes — the
  # prompt after the CEC's REPLY, above all — goes only once the whole chunk is handled, and only
  # if the link still runs then; a restart later in the chunk starts the units afresh instead
  # (two prompts in one session would end the CEC's next command `no_response`).
  defp pump(%{up: true, pumping: true} = s, lun) do
    case {s.waiting[lun], Map.get(s.outbox, lun, [])} do
      {nil, [{function, qualifier, text} | rest]} ->
        text = binary_part(text, 0, min(byte_size(text), Message.max_text()))
        {q, sent} = number(s, lun, qualifier)
        {:ok, message} = Message.new(lun, function, q, text)

        case Protocol.send(s.protocol, Message.encode(message), hold: false) do
          {:ok, protocol, frames, events} ->
            sent = line(%{sent | protocol: protocol}, {protocol, frames, events})
            wait = if function == :read, do: :input, else: :reply
            q = message.qualifier

            %{
              sent
              | waiting: Map.put(sent.waiting, lun, {wait, q}),
                outbox: Map.put(sent.outbox, lun, rest),
                session: Map.update(sent.session, lun, [q], &[q | &1])
            }

          {:error, :not_running} ->
            s
        end

      _ ->
        s
    end
  end

  defp pump(s, _lun), do: s

  defp violation(s), do: %{s | violations: s.violations + 1}

  # An answer that answers nothing waiting: left over from an earlier session when its number
  # was never used in this one, else the CEC broke a rule. Neither is obeyed.
  defp unanswered(s, lun, q, what) do
    if q in Map.get(s.session, lun, []) do
      Logger.warning("VAL II simulator: #{what}, not obeyed")
      violation(s)
    else
      Logger.info("VAL II simulator: #{what}: left over from before the link restarted")
      %{s | stale: s.stale + 1}
    end
  end

  defp number(s, @lun_async, code), do: {code, s}

  defp number(s, lun, _qualifier) do
    n = rem(Map.get(s.numbers, lun, 0), 255) + 1
    {n, %{s | numbers: Map.put(s.numbers, lun, n)}}
  end

  defp now, do: System.monotonic_time(:millisecond)
end
