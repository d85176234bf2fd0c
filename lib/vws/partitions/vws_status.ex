defmodule Vws.Partitions.VwsStatus do
  @moduledoc """
  VWS_STATUS (seed §2.3.6, Fig. 6): the partition that polls DAQ #1, keeps the device-status
  mailbox locations, and runs the actuator requests of the other partitions.

  ## Polling

  Every `:poll_ms` (default 20, the seed's period) it reads every sensor channel of DAQ #1 over
  the HPIB (`Vws.Links.DAQ.poll_commands/1`: the seed's SENSORS/Hp3497 subroutines and their array B),
  converts the readings to millimetres, newtons and switch states (`Vws.Links.DAQ.readings/3`) and
  writes:

    * locations 1–5 and 7 (`GRIPPER`, `TABLE`, `VISE`, `TRAYS`, `VACUUM`, `CHANGER_1`): the texts
      of `Vws.Links.DAQ.DeviceStatus`;
    * location 11 (`SENSORS`): the `Vws.Links.DAQ.Readings` themselves, which the GRIPPER, FIXTURE and
      VACUUM partitions watch to confirm what their commands did (`readings/1`, `await/4`).

  Polls are scheduled on absolute times (`t0 + k · poll_ms`), so a late one does not shift
  the ones after it, and the process runs at high priority, so other work on the node does not
  delay them. A poll that starts more than `:late_after_us` (default 1000 µs) after its
  time counts as **late**; a time that passes while the previous poll is still unanswered (or
  while the process was held up) is **missed** and skipped. `stats/1` shows the counts.

  ## Stale readings

  Old values are never presented as fresh. When no poll has succeeded for `:stale_after_ms`
  (default 200: ten periods), every location it keeps is overwritten with `NO DATA (<why>)` — `DAQ #1 NOT
  ANSWERING` (a poll timed out or is still unanswered), `DAQ #1 NOT CONNECTED`, `DAQ #1 BAD
  ANSWER` — and location 11 with `{:no_data, why}`, until a poll succeeds again. Before the
  first answer they read `NO DATA (DAQ #1 NOT READ YET)`. Started without a link
  (`link: nil`) it writes `NO DATA (NO LINK TO DAQ #1)` and polls nothing.

  Locations that belong to other devices (MONARCH and TLI_TABLE to the GE-2000, WHERE_ROBOT to the
  VAL II, PALLET to the hydraulic controller) say which link they are waiting for until the
  partition of that device writes them.

  ## Actuators

  `actuate/3` is the seed's ACTUATOR/Hp_act: relay channels (or their signal names from the
  channel map) to open or close. VWS_STATUS sends them on the same HPIB device as its polls,
  reads the whole slot (twice, alike) in a transaction of its own, then opens before it closes, and
  confirms the relays with `ROUT:CLOS?` before it answers `:ok`; a
  relay that does not read back as commanded is set and read again (at most twice, counted in
  telemetry), as the command or its answer may have been damaged on the line. An answer
  missing or damaged even after the bus's own tries counts as a try: the slot is read again
  and a relay set again only if it is not as intended (never written blindly). So a third try
  that only reads can find the relay still not set; it then says what kept it from being set:
  `RELAY 209 NOT AS COMMANDED AFTER DAQ #1 NOT ANSWERING (NO ANSWER IN 1000 MS)`. A
  reading taken after that has `requested_at` later than the moment `actuate/3` returned, which
  is what `await/4` waits for.

  Actuations run one at a time, each with all its tries, in the order they were asked (a button's
  press and its release too): the intended state of a write and of its corrections is the whole
  slot as that actuation read it, so a write of another partition landing between its tries
  would read as "not as commanded" and be set back, that partition's command already confirmed.
  One that waited behind the others so long that its caller would give up before its tries end
  is never sent: `DAQ #1 RELAYS BUSY`.

  `push_button/3` closes a relay briefly (the cycle-start button);
  `cycle_start_fun/2` and `tray_lock_fun/2` build the functions MONARCH and ROBOT are given.

  A button is never left pressed: VWS_STATUS holds the press and lets it go itself, so a press
  outlives the command that asked for it (a MONARCH killed mid-press); a release that fails (the
  DAQ gone) is tried again at every poll until a release is confirmed; and VWS_STATUS starts by
  letting go of every button (`:cycle_start_relay`), which a predecessor killed mid-press may
  have left held.

  ## Options

  `:workstation`; `:link` — the HPIB device `{bus, address}` of DAQ #1, or nil; `:poll_ms`;
  `:timeout_ms` — how long one poll or actuation may take on the HPIB (default 500);
  `:stale_after_ms`; `:late_after_us`; `:min_force_n` (VISE "LOCKED" threshold, default 800);
  `:wake_early_us` — wake this long (rounded up to ms) before each slot and wait for it on the
  CPU (default 0: sleep until the slot). An OS wakes a sleeping thread late by up to a few ms
  (on the 2-core VM of `bench/vws_status_poll.exs`, p99 0.4–2.5 ms for the BEAM's own timers);
  2000 µs takes that out of the poll period for about 8 % of one core per workstation — the
  setting for a workstation alone on its host (`config/runtime.exs`), not for hundreds on one
  node;
  `:daq` — `Vws.Links.DAQ.new/1` options (`:channel_map`, `:switches`);
  `:shedding` — the load-shedding pool it belongs to (default `:node`, or the application's
  `:vws_status_shedding`; `false`: none) and
  `:max_period_ms` (default 100), the longest period shedding may stretch its polls to, never
  more than half of `:stale_after_ms` (`Vws.Partitions.VwsStatus.Shedding`).

  ## Load shedding

  When the node cannot make every workstation's polls on time, the polls of every workstation
  are stretched alike (`Vws.Partitions.VwsStatus.Shedding`): each polls every `k · poll_ms`,
  at least every `:max_period_ms`. The staleness rule above is unchanged: what could not be
  read fresh in `:stale_after_ms` reads `NO DATA`, and `await/4` takes only readings requested
  after its start, so a slower poll makes a command wait longer or end `ERROR`, never act on an
  older reading. `stats/1` gives the period in force (`period_ms`).

  ## Sensors

  What it knows of DAQ #1's sensors and relays without a process — the locations and what they
  hold without a fresh reading, how location 11 reads, the values of signals for a check
  (`Vws.Partitions.VwsStatus.Sensors.values/3`, which GRIPPER, FIXTURE and VACUUM use), the
  tray locks, how an HPIB answer reads as a command status — is `Vws.Partitions.VwsStatus.Sensors`.

  ## Telemetry

  `[:vws, :vws_status, :poll | :missed | :stale | :actuation_retry]`, with their measurements
  and metadata in the catalogue of `Vws.Telemetry`. At every write of location 11 it causes
  the workstation's `:sensors` event (`Vws.CEC.Events`), which `await/4` waits on.
  """
  use GenServer
  require Logger

  alias Vws.Links.{DAQ, HPIB}
  alias Vws.CEC.Mailbox
  alias Vws.Links.DAQ.{DeviceStatus, Readings}
  alias Vws.Partitions.VwsStatus.{Sensors, Shedding}

  @device "DAQ #1"
  # how many times an actuation whose relays are not as commanded is sent again
  @actuation_retries 2
  # at most: the reads before the write and the write, then a transaction for each retry
  @actuation_transactions @actuation_retries + 2

  @defaults [
    poll_ms: 20,
    timeout_ms: 500,
    stale_after_ms: 200,
    late_after_us: 1_000,
    min_force_n: 800,
    wake_early_us: 0,
    max_period_ms: 100
  ]

  @type workstation :: term
  @type action :: {DAQ.signal() | pos_integer, :open | :close}

  @doc false
  def child_spec(opts), do: %{id: :vws_status, start: {__MODULE__, :start_link, [opts]}}

  @doc "Starts VWS_STATUS for a workstation; see the options above."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    GenServer.start_link(__MODULE__, opts, name: Vws.CEC.Partition.via(ws, :vws_status))
  end

  ## Client API

  @doc """
  The latest readings of DAQ #1 from mailbox location 11: `{:ok, readings}`, or
  `{:no_data, why}` when there are none or they went stale.
  """
  @spec readings(workstation) :: {:ok, Readings.t()} | {:no_data, String.t()}
  def readings(ws) do
    {value, _age} = Mailbox.get_device(ws, Sensors.sensors_location())
    Sensors.reading(value)
  end

  @doc """
  Sets relays of DAQ #1 — `[{signal_or_channel, :open | :close}]` — and confirms them with
  `ROUT:CLOS?`. Returns `:ok` or `{:error, reason}` with the reason as a command status shows it
  (`DAQ #1 NOT ANSWERING (NO ANSWER IN 500 MS)`, `RELAY 206 NOT AS COMMANDED`, …).
  """
  @spec actuate(workstation, [action], timeout) :: :ok | {:error, String.t()}
  def actuate(ws, actions, timeout \\ 5_000) do
    GenServer.call(
      Vws.CEC.Partition.via(ws, :vws_status),
      {:actuate, actions, deadline(timeout)},
      timeout
    )
  catch
    :exit, {:timeout, _} -> {:error, "#{@device} NOT ANSWERING (NO ANSWER IN #{timeout} MS)"}
    :exit, _ -> {:error, "VWS_STATUS NOT RUNNING"}
  end

  @doc """
  Waits until a reading requested after `since` (monotonic µs, taken right after `actuate/3`)
  satisfies `check`. `check` gets each fresh reading once — with the fresh reading before it
  (or nil) if it takes two arguments, to see whether something still moves — and returns `:ok`,
  `{:wait, what_was_read}` (not yet), or `{:fail, what_was_read}` (it never will: stop now).

  `:ok` counts when two fresh readings in a row give it (a reading damaged on the line must not
  confirm anything). Returns `:ok`, or `{:error, what_was_read}`: at a `:fail`, or after
  `timeout_ms` with the last
  fresh reading's `what` — or, when no fresh reading came at all, the stale reason or
  `DAQ #1 NOT ANSWERING (NO FRESH READING IN n MS)`.
  """
  @spec await(workstation, integer, non_neg_integer, check) :: :ok | {:error, String.t()}
        when check: (Readings.t() -> verdict) | (Readings.t(), Readings.t() | nil -> verdict),
             verdict: :ok | {:wait, String.t()} | {:fail, String.t()}
  def await(ws, since, timeout_ms, check) do
    check = if is_function(check, 1), do: fn r, _prev -> check.(r) end, else: check
    deadline = System.monotonic_time(:millisecond) + timeout_ms
    acc = %{prev: nil, read: nil, no_data: nil, confirming: false}
    # subscribed before the first read: a reading written after it wakes us
    :ok = Vws.CEC.Events.subscribe(ws, :sensors)

    try do
      do_await(ws, since, deadline, timeout_ms, check, acc)
    after
      Vws.CEC.Events.unsubscribe(ws, :sensors)
      flush_sensor_events(ws)
    end
  end

  defp flush_sensor_events(ws) do
    receive do
      {:vws_event, ^ws, :sensors, _} -> flush_sensor_events(ws)
    after
      0 -> :ok
    end
  end

  defp do_await(ws, since, deadline, timeout_ms, check, acc) do
    {verdict, acc} =
      case readings(ws) do
        {:ok, %Readings{requested_at: at} = r} when at > since ->
          if acc.prev != nil and acc.prev.seq == r.seq do
            {:wait, acc}
          else
            case check.(r, acc.prev) do
              # one reading may have been damaged on the line: the next fresh one must agree
              :ok when acc.confirming -> {:ok, acc}
              :ok -> {:wait, %{acc | prev: r, confirming: true}}
              {:wait, what} -> {:wait, %{acc | prev: r, read: what, confirming: false}}
              {:fail, what} -> {{:fail, what}, acc}
            end
          end

        {:ok, _older} ->
          {:wait, acc}

        {:no_data, why} ->
          {:wait, %{acc | no_data: why}}
      end

    now = System.monotonic_time(:millisecond)

    cond do
      verdict == :ok ->
        :ok

      match?({:fail, _}, verdict) ->
        {:error, elem(verdict, 1)}

      now > deadline ->
        # what was read says most; failing that, why nothing could be read
        {:error,
         acc.read || acc.no_data ||
           "#{@device} NOT ANSWERING (NO FRESH READING IN #{timeout_ms} MS)"}

      true ->
        # the next write of location 11 (a reading, or NO DATA) — or the deadline, passed
        receive do
          {:vws_event, ^ws, :sensors, _} -> :ok
        after
          deadline - now + 1 -> :ok
        end

        do_await(ws, since, deadline, timeout_ms, check, acc)
    end
  end

  @doc """
  Runs one device command the way GRIPPER, FIXTURE and VACUUM do: `actuate/3`, then `await/4`
  until the sensors confirm. Returns a partition result: `:done` or `{:error, reason}`.
  """
  @spec operate(workstation, [action], non_neg_integer, function) :: :done | {:error, String.t()}
  def operate(ws, actions, timeout_ms, check) do
    with :ok <- actuate(ws, actions),
         :ok <- await(ws, System.monotonic_time(:microsecond), timeout_ms, check) do
      :done
    end
  end

  @doc """
  Presses a button wired to a relay: closes it, holds it `pulse_ms`, opens it. `:ok` only if both
  were confirmed.
  """
  @spec push_button(workstation, DAQ.signal() | pos_integer, non_neg_integer) ::
          :ok | {:error, String.t()}
  def push_button(ws, relay, pulse_ms, timeout \\ 5_000) do
    # VWS_STATUS holds the press and lets it go, whatever becomes of the caller
    GenServer.call(
      Vws.CEC.Partition.via(ws, :vws_status),
      {:push, relay, pulse_ms, deadline(pulse_ms + 2 * timeout)},
      pulse_ms + 2 * timeout
    )
  catch
    :exit, {:timeout, _} -> {:error, "#{@device} NOT ANSWERING (NO ANSWER IN #{timeout} MS)"}
    :exit, _ -> {:error, "VWS_STATUS NOT RUNNING"}
  end

  # when the caller stops waiting for its answer (monotonic ms)
  defp deadline(:infinity), do: :infinity
  defp deadline(timeout), do: System.monotonic_time(:millisecond) + timeout

  @doc """
  The function MONARCH's CYCLE_START calls (`ctx.options[:cycle_start]`): presses the
  cycle-start relay (`:cycle_start_relay`) for `:pulse_ms` (default 200).
  """
  @spec cycle_start_fun(workstation, keyword) :: (() -> :ok | {:error, String.t()})
  def cycle_start_fun(ws, opts \\ []) do
    pulse = Keyword.get(opts, :pulse_ms, 200)
    fn -> push_button(ws, :cycle_start_relay, pulse) end
  end

  @doc """
  The function ROBOT's DISABLE_TRAYn / RELEASE_TRAYn call (`ctx.options[:tray_lock]`, with
  `:lock` and `:release` — `:unlock` is the same): sets the tray's lock relay and waits
  (`:timeout_ms`, default 2000) until its lock-pin switch confirms.
  """
  @spec tray_lock_fun(workstation, keyword) ::
          (1 | 2, :lock | :release | :unlock -> :ok | {:error, String.t()})
  def tray_lock_fun(ws, opts \\ []) do
    timeout = Keyword.get(opts, :timeout_ms, 2_000)
    fn tray, how -> tray_lock(ws, tray, how, timeout) end
  end

  @doc "Locks or unlocks tray 1 or 2 and confirms it on its lock-pin switch."
  @spec tray_lock(workstation, 1 | 2, :lock | :release | :unlock, non_neg_integer) ::
          :ok | {:error, String.t()}
  def tray_lock(ws, tray, how, timeout_ms) do
    {action, check} = Sensors.tray_lock(tray, how)

    with :ok <- actuate(ws, [action]),
         do: await(ws, System.monotonic_time(:microsecond), timeout_ms, check)
  end

  @doc """
  Poll statistics: `%{polls, ok, failed, missed, late, stale, last_error, poll_ms,
  consecutive_failures, max_lateness_us, actuations, releases}`; `stale` is nil or the reason
  shown, `actuations` the requests of other partitions (a button's press counts, its release
  not), `releases` the buttons VWS_STATUS let go of itself.
  """
  @spec stats(workstation) :: map
  def stats(ws), do: GenServer.call(Vws.CEC.Partition.via(ws, :vws_status), :stats)

  @doc """
  What a workstation needs to reach DAQ #1 at `endpoint`: the HPIB device child spec for its
  links supervisor, and the partition options — the link of VWS_STATUS, GRIPPER, FIXTURE and
  VACUUM, MONARCH's `cycle_start` and ROBOT's `tray_lock`. Options: `:address` (default 9, the
  HP 3497A's factory address), `:hpib` (`Vws.Links.HPIB.start_link/1` options), `:vws_status`
  (options of this partition), `:pulse_ms`.
  """
  @spec wiring(workstation, String.t() | Vws.Links.Endpoint.t(), keyword) ::
          %{links: [Supervisor.child_spec()], partitions: keyword}
  def wiring(ws, endpoint, opts \\ []) do
    address = Keyword.get(opts, :address, 9)
    link = {ws, address}

    hpib =
      HPIB.child_spec(
        [bus: ws, address: address, endpoint: endpoint, device: @device] ++
          Keyword.get(opts, :hpib, [])
      )

    %{
      links: [hpib],
      partitions: [
        vws_status: [link: link] ++ Keyword.get(opts, :vws_status, []),
        gripper: [link: link],
        fixture: [link: link],
        vacuum: [link: link],
        monarch: [options: [cycle_start: cycle_start_fun(ws, Keyword.take(opts, [:pulse_ms]))]],
        robot: [options: [tray_lock: tray_lock_fun(ws)]]
      ]
    }
  end

  ## Server

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    # its log lines say which workstation they are about, as the other partitions' do
    Logger.metadata(workstation: ws, partition: :vws_status)
    # written at every poll: found without a Registry look-up (looked up again if it is new)
    Mailbox.keep_table(ws)
    opts = Keyword.merge(@defaults, opts)
    link = Keyword.get(opts, :link)
    # caused at every write of location 11: what await/4 waits on
    Vws.CEC.Events.create(ws, :sensors)

    configured = Keyword.get(opts, :devices, [])

    # a configured device has not been read yet; an unconfigured one has no link at all
    for {loc, text} <- Sensors.other_locations(configured),
        Mailbox.get_device(ws, loc) |> elem(0) == nil,
        do: Mailbox.put_device(ws, loc, text)

    if link == nil do
      write_no_data(ws, "NO LINK TO #{@device}")
      {:ok, %{workstation: ws, link: nil}}
    else
      write_no_data(ws, "#{@device} NOT READ YET")
      # The poll's timing is the product (seed: every 20 ms): the scheduler runs this process
      # ahead of the normal ones. It does a few hundred microseconds of work per poll.
      Process.flag(:priority, :high)
      now = System.monotonic_time(:millisecond)
      poll_ms = Keyword.fetch!(opts, :poll_ms)

      s = %{
        workstation: ws,
        link: link,
        daq: DAQ.new(Keyword.get(opts, :daq, [])),
        poll_ms: poll_ms,
        timeout_ms: Keyword.fetch!(opts, :timeout_ms),
        stale_after_ms: Keyword.fetch!(opts, :stale_after_ms),
        late_after_us: Keyword.fetch!(opts, :late_after_us),
        min_force_n: Keyword.fetch!(opts, :min_force_n),
        wake_early_ms: div(Keyword.fetch!(opts, :wake_early_us) + 999, 1000),
        shedding:
          Keyword.get_lazy(opts, :shedding, fn ->
            Application.get_env(:vws, :vws_status_shedding, :node)
          end),
        max_period_ms: Keyword.fetch!(opts, :max_period_ms),
        next_slot: now + poll_ms,
        poll: nil,
        # the actuation on the bus (all its tries) and those waiting for it: one at a time, so
        # that each one's whole-slot expectation is the slot's (see "Actuators")
        actuation: nil,
        waiting: :queue.new(),
        # buttons whose release is not confirmed (a predecessor may have held one: all of
        # them at start), and how many releases are on their way
        unreleased: Sensors.buttons(Keyword.get(opts, :daq, [])),
        releasing: 0,
        seq: 0,
        last_good_at: now,
        stale: "#{@device} NOT READ YET",
        stats: %{
          polls: 0,
          ok: 0,
          failed: 0,
          missed: 0,
          late: 0,
          max_lateness_us: 0,
          consecutive_failures: 0,
          last_error: nil,
          actuations: 0,
          releases: 0
        }
      }

      {:ok, schedule(s)}
    end
  end

  @impl true
  def handle_call({:actuate, _actions, _deadline}, _from, %{link: nil} = s),
    do: {:reply, {:error, "NO LINK TO #{@device}"}, s}

  def handle_call({:actuate, actions, deadline}, from, s) do
    case DAQ.actuation(s.daq, actions) do
      {:error, {:unknown_actuator, who}} ->
        {:reply, {:error, "UNKNOWN ACTUATOR #{Vws.Codecs.WC.Words.of(who)}"}, s}

      {:ok, [], []} ->
        {:reply, :ok, s}

      {:ok, commands, expected} ->
        {:noreply, request(s, commands, expected, from, latest_start(s, deadline, 0))}
    end
  end

  def handle_call({:push, _relay, _pulse_ms, _deadline}, _from, %{link: nil} = s),
    do: {:reply, {:error, "NO LINK TO #{@device}"}, s}

  def handle_call({:push, relay, pulse_ms, deadline}, from, s) do
    case DAQ.actuation(s.daq, [{relay, :close}]) do
      {:error, {:unknown_actuator, who}} ->
        {:reply, {:error, "UNKNOWN ACTUATOR #{Vws.Codecs.WC.Words.of(who)}"}, s}

      {:ok, commands, expected} ->
        # this press is let go at its own time: an earlier release must not cut it short
        s = %{s | unreleased: MapSet.delete(s.unreleased, relay)}
        # the caller also waits for the pulse and the release
        latest = latest_start(s, deadline, pulse_ms + @actuation_transactions * s.timeout_ms)
        {:noreply, request(s, commands, expected, {:pressed, relay, pulse_ms, from}, latest)}
    end
  end

  def handle_call(:stats, _from, %{link: nil} = s),
    do: {:reply, %{link: nil, stale: "NO LINK TO #{@device}"}, s}

  def handle_call(:stats, _from, s) do
    {:reply,
     Map.merge(s.stats, %{stale: s.stale, poll_ms: s.poll_ms, period_ms: period(s), link: s.link}),
     s}
  end

  @impl true
  def handle_info({:timeout, _ref, :tick}, s), do: {:noreply, tick(s)}

  def handle_info({:let_go, relay, caller}, s) do
    s = %{s | unreleased: MapSet.put(s.unreleased, relay)}
    {:noreply, release(s, [relay], caller)}
  end

  def handle_info(msg, %{link: link} = s) when link != nil do
    case s.poll && HPIB.check_response(msg, s.poll.req) do
      result when result in [nil, :no_reply] -> {:noreply, actuation_reply(msg, s)}
      result -> {:noreply, poll_answered(result, s)}
    end
  end

  def handle_info(msg, s) do
    Logger.debug("VWS_STATUS: unexpected message #{inspect(msg, limit: 10)}")
    {:noreply, s}
  end

  ## Polling

  defp schedule(s) do
    :erlang.start_timer(s.next_slot - s.wake_early_ms, self(), :tick, abs: true)
    s
  end

  # Woken `wake_early_ms` before the slot, the process waits for it on the CPU (yielding to
  # every other runnable process): the OS wakes a sleeping thread up to a few ms late, a running
  # one needs no waking.
  defp wait_for_slot(%{wake_early_ms: 0}), do: :ok

  defp wait_for_slot(s) do
    if System.monotonic_time(:microsecond) < s.next_slot * 1000 do
      :erlang.yield()
      wait_for_slot(s)
    else
      :ok
    end
  end

  defp tick(s) do
    wait_for_slot(s)
    started = System.monotonic_time(:microsecond)
    lateness = started - s.next_slot * 1000

    s =
      if s.poll do
        missed(s, :busy, 1)
      else
        req = HPIB.send_request(s.link, DAQ.poll_commands(s.daq), s.timeout_ms)
        seq = s.seq + 1
        late = if lateness > s.late_after_us, do: 1, else: 0

        # the node overloaded, not the OS waking a thread a few ms late: half a period late
        shed(s, 1, if(lateness * 2 > period(s) * 1000, do: 1, else: 0), 0)

        stats = s.stats

        %{
          s
          | poll: %{req: req, seq: seq, started: started, lateness: lateness, handling: 0},
            seq: seq,
            stats: %{
              stats
              | polls: stats.polls + 1,
                late: stats.late + late,
                max_lateness_us: max(stats.max_lateness_us, lateness)
            }
        }
      end

    s = check_stale(s, div(started, 1000))

    # a button still held: try again to let it go
    s =
      if s.releasing == 0 and MapSet.size(s.unreleased) > 0,
        do: release(s, MapSet.to_list(s.unreleased), nil),
        else: s

    # the next slot still ahead of us, at the period the node's load allows (Shedding); the
    # ones already gone are missed
    period = period(s)
    now = System.monotonic_time(:millisecond)
    next = s.next_slot + period
    skipped = if next <= now, do: div(now - next, period) + 1, else: 0
    s = if skipped > 0, do: missed(s, :held_up, skipped), else: s
    s = %{s | next_slot: next + skipped * period}

    s =
      if s.poll,
        do: put_in(s.poll.handling, System.monotonic_time(:microsecond) - started),
        else: s

    schedule(s)
  end

  defp poll_answered(result, s) do
    t0 = System.monotonic_time(:microsecond)
    poll = s.poll
    s = %{s | poll: nil}

    s =
      case result do
        {:ok, answers} ->
          readings =
            DAQ.readings(s.daq, answers,
              seq: poll.seq,
              requested_at: poll.started,
              received_at: t0
            )

          texts = DeviceStatus.text_list(readings, min_force_n: s.min_force_n)

          # the texts, then location 11 and the event that wakes whoever awaits a reading (await/4)
          Mailbox.put_devices(
            s.workstation,
            texts ++ [{Sensors.sensors_location(), readings, :changed}]
          )

          Vws.CEC.Events.cause(s.workstation, :sensors)

          # the stale readings' warning ends here, with how often it was repeated
          Vws.LogLimit.clear(:stale, "VWS_STATUS: #{@device} answers again")

          stats = s.stats

          %{
            s
            | last_good_at: div(t0, 1000),
              stale: nil,
              stats: %{stats | ok: stats.ok + 1, consecutive_failures: 0}
          }

        {:error, error} ->
          s
          |> update_stats(failed: 1, consecutive_failures: 1)
          |> put_in([:stats, :last_error], error)
          |> check_stale(div(t0, 1000))
      end

    # what each poll took, for whoever listens (bench/vws_status_poll.exs): not built for nobody
    if Vws.Telemetry.listened?([:vws, :vws_status, :poll]) do
      handling = poll.handling + System.monotonic_time(:microsecond) - t0

      Vws.Telemetry.execute(
        [:vws, :vws_status, :poll],
        %{
          started_at: poll.started,
          lateness: poll.lateness,
          duration: t0 - poll.started,
          handling: handling
        },
        %{workstation: s.workstation, seq: poll.seq, result: poll_result(result)}
      )
    end

    s
  end

  defp poll_result({:ok, _}), do: :ok
  defp poll_result({:error, %{reason: reason}}), do: {:error, reason}

  defp period(%{shedding: false} = s), do: s.poll_ms

  # never longer than half the time after which readings are shown stale: staleness is
  # checked at every tick
  defp period(s) do
    max_period = min(s.max_period_ms, div(s.stale_after_ms, 2))
    Shedding.period(s.poll_ms, Shedding.stretch(s.shedding), max_period)
  end

  defp shed(%{shedding: false}, _due, _late, _missed), do: :ok
  defp shed(s, due, late, missed), do: Shedding.count(s.shedding, due, late, missed)

  defp missed(s, reason, n) do
    shed(s, n, 0, n)

    Vws.Telemetry.execute([:vws, :vws_status, :missed], %{count: n}, %{
      workstation: s.workstation,
      reason: reason
    })

    update_stats(s, missed: n)
  end

  defp update_stats(s, increments) do
    stats = Enum.reduce(increments, s.stats, fn {k, n}, acc -> Map.update!(acc, k, &(&1 + n)) end)
    %{s | stats: stats}
  end

  # No good poll for stale_after_ms: the texts must not go on showing the old values.
  defp check_stale(s, now_ms) do
    if now_ms - s.last_good_at > s.stale_after_ms do
      why = Sensors.stale_reason(s.stats.last_error, s.poll != nil, s.stale)

      if why != s.stale do
        # once per outage, not per reason it gives (NOT CONNECTED, NOT ANSWERING alternate at
        # every poll of a DAQ that is gone: 150 lines a second)
        Vws.LogLimit.warning(:stale, "VWS_STATUS: readings are stale: #{why}")

        Vws.Telemetry.execute([:vws, :vws_status, :stale], %{count: 1}, %{
          workstation: s.workstation,
          reason: why
        })

        write_no_data(s.workstation, why)
        %{s | stale: why}
      else
        s
      end
    else
      s
    end
  end

  defp write_no_data(ws, why) do
    for {loc, value} <- Sensors.no_data(why), do: Mailbox.put_device(ws, loc, value)
    Vws.CEC.Events.cause(ws, :sensors)
  end

  ## Actuations

  # One actuation of the slot at a time, with all its tries: each one's expectation — every
  # relay it does not command as the reads before its write found it, and a correction's whole
  # slot — then holds until it ends. Two in flight at once, a correction of one (after a
  # damaged line) would find the other's relay "not as commanded" and set it back.
  defp request(s, commands, expected, from, latest_start, counter \\ :actuations) do
    s = update_in(s.stats[counter], &(&1 + 1))

    if s.actuation == nil,
      do: send_actuation(s, {commands, expected, 1, nil}, from),
      else: %{s | waiting: :queue.in({commands, expected, from, latest_start}, s.waiting)}
  end

  # The latest moment (monotonic ms) an actuation may start after waiting for others: its
  # caller must still be waiting when its tries (and `after_ms` more) have had their time.
  defp latest_start(_s, :infinity, _after_ms), do: :infinity

  defp latest_start(s, deadline, after_ms),
    do: deadline - @actuation_transactions * s.timeout_ms - after_ms

  defp next_actuation(%{actuation: nil} = s) do
    case :queue.out(s.waiting) do
      {:empty, _} ->
        s

      {{:value, {commands, expected, from, latest_start}}, waiting} ->
        s = %{s | waiting: waiting}

        # one that waited too long is never sent: its caller could give up before its end
        if latest_start == :infinity or System.monotonic_time(:millisecond) <= latest_start do
          send_actuation(s, {commands, expected, 1, nil}, from)
        else
          next_actuation(actuated(from, {:error, "#{@device} RELAYS BUSY"}, s))
        end
    end
  end

  defp next_actuation(s), do: s

  # `act`: `{commands, expected, try, unanswered}` — `unanswered`, the reason the try before
  # failed when its answers were missing or damaged (this one then only reads the slot)
  defp send_actuation(s, {commands, _expected, _try, _unanswered} = act, from) do
    req = HPIB.send_request(s.link, commands, s.timeout_ms)
    %{s | actuation: {req, from, act}}
  end

  defp actuation_reply(msg, s) do
    with {req, _from, {_, expected, _, _}} = a <- s.actuation,
         result when result != :no_reply <- HPIB.check_response(msg, req) do
      actuation_result(a, Sensors.actuation_result(result, expected), s)
    else
      _ ->
        Logger.debug("VWS_STATUS: unexpected message #{inspect(msg, limit: 10)}")
        s
    end
  end

  # the slot read before the write: the write goes out, in the same try
  defp actuation_result({_req, from, {_, _, try, _}}, {:next, commands, expected}, s),
    do: send_actuation(s, {commands, expected, try, nil}, from)

  defp actuation_result({_req, from, {_commands, expected, try, _}}, {:error, failure}, s)
       when is_tuple(failure) and elem(failure, 0) in [:relays, :damaged] and
              try <= @actuation_retries do
    Vws.Telemetry.execute([:vws, :vws_status, :actuation_retry], %{count: 1}, %{
      workstation: s.workstation,
      reason: elem(failure, 1),
      try: try
    })

    {commands, expected} = retry(failure, expected)
    unanswered = if elem(failure, 0) == :damaged, do: elem(failure, 1)
    send_actuation(s, {commands, expected, try + 1, unanswered}, from)
  end

  defp actuation_result({_req, from, {_, _, _, unanswered}}, reply, s) do
    reply =
      case reply do
        # the last try could only read: it says why it could not set the relay right
        {:error, {:relays, why, _results}} when unanswered != nil ->
          {:error, "#{why} AFTER #{unanswered}"}

        {:error, {:relays, why, _results}} ->
          {:error, why}

        {:error, {:damaged, why}} ->
          {:error, why}

        other ->
          other
      end

    next_actuation(actuated(from, reply, %{s | actuation: nil}))
  end

  # The transaction after a failed one. A relay of the slot not as intended (the command or
  # the answer may have been damaged on the line): the wrong relays set right and the whole
  # slot confirmed again. Answers damaged or missing even after the bus's own tries: the writes
  # may have been done, so the slot is read again (DAQ.recheck/1) and a relay is set again only
  # if those reads show it is not as intended — never written blindly.
  defp retry({:relays, _why, results}, expected) do
    {:ok, commands, expected} = DAQ.correction(expected, results)
    {commands, expected}
  end

  defp retry({:damaged, _why}, expected), do: {DAQ.recheck(expected), expected}

  # The relays to let go: `caller` (or nil) is told how it went.
  defp release(s, relays, caller) do
    {:ok, commands, expected} = DAQ.actuation(s.daq, Enum.map(relays, &{&1, :open}))
    s = request(s, commands, expected, {:released, relays, caller}, :infinity, :releases)
    %{s | releasing: s.releasing + 1}
  end

  # A press confirmed is let go after its pulse; one that failed may have half-happened.
  defp actuated({:pressed, relay, pulse_ms, caller}, :ok, s) do
    Process.send_after(self(), {:let_go, relay, caller}, pulse_ms)
    s
  end

  defp actuated({:pressed, relay, _pulse_ms, caller}, error, s) do
    GenServer.reply(caller, error)
    %{s | unreleased: MapSet.put(s.unreleased, relay)}
  end

  defp actuated({:released, relays, caller}, reply, s) do
    s = %{s | releasing: s.releasing - 1}

    case reply do
      :ok ->
        if caller, do: GenServer.reply(caller, :ok)
        names = Enum.map_join(relays, ", ", &Sensors.relay_name/1)
        Vws.LogLimit.clear({:not_released, relays}, "VWS_STATUS: #{names} let go")
        %{s | unreleased: MapSet.difference(s.unreleased, MapSet.new(relays))}

      {:error, why} ->
        names = Enum.map_join(relays, ", ", &Sensors.relay_name/1)

        # once until it is let go, not at every try
        Vws.LogLimit.warning(
          {:not_released, relays},
          "VWS_STATUS: #{names} not let go (#{why}); trying again until it is"
        )

        if caller, do: GenServer.reply(caller, {:error, "RELAY #{names} NOT RELEASED: " <> why})
        s
    end
  end

  defp actuated(from, reply, s) do
    GenServer.reply(from, reply)
    s
  end
end
