defmodule Vws.Test.CrashCampaign do
  @moduledoc """
  Issue 8's crash campaign (`Vws.Reliability.CrashTest`): each link and each partition process of a workstation killed
  `@kills` times at random moments (a fixed seed), while a WC runs the shipped machining cycle
  (`priv/sims/machining_cycle.vws`) over and over on the whole simulated floor
  (`Vws.Sim.Floor`, time-scaled so that a cycle takes about two seconds).

  Killed: every child of the workstation's links supervisor (the robot's `Vws.Links.VAL`, MONARCH's
  DNC link and its status monitor, DAQ #1's and the hydraulic controller's HPIB devices, the
  PALLET monitor), the DDCMP link under `Vws.Links.VAL`, and the seven partitions (VWS_STATUS, ROBOT,
  MONARCH, GRIPPER, FIXTURE, VACUUM, HYDRAULIC). One killer per supervisor, side by side, each
  spacing its kills so that its supervisor never meets its restart intensity (50 restarts in
  5 s, counted in whole seconds): at most `@per_window` kills in any 6 s.

  The WC does what a WC does: a cycle that meets an `ERROR` (or an `EXPECT` that fails) stops,
  the cell is cleared (the robot sent home, leases given back, the gripper opened, the part put
  back in tray #1 by the "operator") and the next cycle starts.

  What is checked, from the CEC's own telemetry (commands dispatched by SUN_COMM, finished by the
  partitions) and the simulators' (`[:vws, :sim, …]`: every relay a DAQ wrote, every monitor
  command the VAL II obeyed, every program the GE-2000 stored or selected):

    * SUN_COMM is the same process throughout, its WC connection stays up (one connection, the
      client never reconnected), and the mailbox table is the same table;
    * every command dispatched ends exactly once, `DONE` or `ERROR <reason>` with a reason; a
      command in flight in a partition that is killed ends `ERROR` (`INTERRUPTED BY PARTITION
      RESTART`), and no cycle stopped because a command never ended (the link kills end theirs
      `VAL II LINK DOWN`, `DNC LINK DOWN`, `NO LINK TO DAQ #1`, `VWS_STATUS NOT RUNNING`, …);
    * the mailboxes still hold each partition's last command with its true status;
    * no command ran on the equipment more than once: each physical execution is matched to the
      latest command of its kind dispatched before it (a motion to the `DO` of the same
      instruction, a relay write to the command that writes that relay, a stored program to
      `DOWNLOAD_GE`), and no command gets two, while each command `DONE` got its one. A relay
      write is repeatable (it sets a state, `Vws.Codecs.SCPI.repeatable?/1`): the HPIB device
      sends it again when its answer is late or damaged, and on a starved machine the late try
      reaches the DAQ too; as many executions as the bus's retries of that write are the bus's,
      not the command run again;
    * after the campaign no button is left pressed (the cycle-start relay is open) and, with
      the cell cleared, a clean cycle completes.

  The test prints its figures: kills, cycles (about 105, a dozen completed), commands (about
  2 600), commands in flight in a killed partition (about 60), physical executions (about
  1 900) and what stopped the cycles.

  The targets are shared out among `Vws.Reliability.CrashTest`'s groups, each its own
  workstation and floor with links and partitions killed side by side: every target is still
  killed `@kills` times, and the groups run at once. One campaign of all thirteen targets took
  about 112 s on a loaded 2-core machine, nearly all of it the killers' pacing (700 kills one
  after the other at 40–240 ms, never more than the supervisor's restart intensity allows);
  a group of a third of them takes about a third of that.
  """
  import ExUnit.Assertions
  import ExUnit.Callbacks, only: [start_supervised!: 1, on_exit: 1]
  import Vws.Test.Eventually

  alias Vws.Peers.HydraulicController
  alias Vws.CEC.{Mailbox, Partition, SunComm}
  alias Vws.Sim.{Floor, Plant}
  alias Vws.Peers.WC.{Client, ClientError, Runner, Script}
  alias Vws.CEC.Workstation, as: WS

  @kills 100
  @seed {1988, 6, 9}
  # gaps between the kills of one killer, ms, uniform
  @gap 40..240
  # at most this many kills per supervisor in any 5 s (its intensity is 50 in 5 s)
  @per_window 42
  @window_ms 5_000
  @time_scale 50
  @command_ms 20_000

  @partitions [:vws_status, :robot, :monarch, :gripper, :fixture, :vacuum, :hydraulic]

  @doc "A workstation on the whole simulated floor, its events recorded, a WC connected."
  def setup_cell do
    ws = "crash-#{System.unique_integer([:positive])}"

    start_supervised!(
      {Floor,
       workstation: ws,
       time_scale: @time_scale,
       hydraulic: {HydraulicController, []},
       ge2000: true,
       robot: true,
       mhs: true}
    )

    :ok = HydraulicController.await_ready(Floor.hydraulic_controller(ws), 10_000)
    :ok = Plant.set_part(Floor.plant(ws), :tray1, true)

    interlock = [interlock: [timeout: 2_000, retry_ms: 50]]

    %{wc: wc} =
      Vws.Test.Workstation.start(
        id: ws,
        devices: Floor.devices(ws),
        partitions: [
          robot: [options: [command_timeout: 5_000, motion_timeout: 15_000] ++ interlock],
          fixture: [options: interlock],
          monarch: [options: interlock]
        ]
      )

    assert eventually(fn -> SunComm.listening(ws) != nil end)
    events = record(ws)
    {:ok, client} = Client.connect(wc)

    {:ok, script} = Script.parse_file(Vws.Ops.Demo.default_script())
    # the script's TIMEOUT 900 for a real machine: the simulated one takes a second
    steps =
      for step <- script.steps do
        if match?({:timeout, _}, step.op), do: %{step | op: {:timeout, @command_ms}}, else: step
      end

    %{ws: ws, client: client, events: events, script: %{script | steps: steps}}
  end

  @doc """
  The campaign on the `group`th of `groups` shares of the targets (every `groups`th link and
  partition, from the `group`th): each killed `@kills` times while the WC runs cycles.
  """
  def run(ctx, {group, groups}) do
    %{ws: ws, client: client, events: events} = ctx
    sun_comm = WS.whereis(ws, :sun_comm)
    table = Mailbox.table(ws)
    owner = :ets.info(table, :owner)

    # one clean cycle first: the floor works, and the counting below sees a whole cycle
    assert %{result: :completed} = run_cycle(client, ctx.script)

    wc = Task.async(fn -> cycles(client, ctx.script, ws, []) end)
    kills = campaign(ws, events, {group, groups})
    send(wc.pid, :stop)
    summaries = Task.await(wc, 120_000)

    # SUN_COMM never restarted and its WC connection stayed up; the mailbox table is the same
    assert WS.whereis(ws, :sun_comm) == sun_comm
    assert SunComm.info(ws).counters.connections == 1
    assert Client.info(client).counters.reconnects == 0
    assert Mailbox.table(ws) == table and :ets.info(table, :owner) == owner

    # the WC never waited for a command that did not end
    hung =
      for %{stopped: %{error: %ClientError{reason: r}} = s} <- summaries,
          r in [:command_timeout, :timeout, :closed],
          do: s.reason

    assert hung == []

    # the mailboxes still hold each partition's last command and its true status (a command the
    # WC had sent to another partition when a cycle stopped may still be ending: its end counts)
    eventually(
      fn ->
        Enum.all?(last_finished(events), fn {p, last} -> Mailbox.command_status(ws, p) == last end)
      end,
      30_000
    )

    for {partition, last} <- last_finished(events) do
      assert Mailbox.command_status(ws, partition) == last
    end

    # the cell cleared (and no button left pressed), a clean cycle completes
    settle(ws, client)
    assert eventually(fn -> not Plant.snapshot(Floor.plant(ws)).cycle_start_relay end)
    summary = run_cycle(client, ctx.script)
    assert summary.result == :completed, "the clean cycle stopped: #{inspect(summary.stopped)}"
    assert summary.steps_done == length(ctx.script.steps)

    figures = check(events, kills)

    stops =
      summaries |> Enum.map(&stop_reason/1) |> Enum.frequencies() |> Enum.sort_by(&(-elem(&1, 1)))

    IO.puts(
      "\ncrash campaign #{group + 1}/#{groups}: #{length(kills)} kills; #{length(summaries)} cycles, " <>
        "#{Enum.count(summaries, &(&1.result == :completed))} completed; " <>
        "#{figures.dispatched} commands, #{figures.interrupted} in flight in a killed partition, " <>
        "#{figures.executed} physical executions (#{figures.bus_retried} of them a relay write " <>
        "the HPIB sent again); cycles stopped by: " <>
        Enum.map_join(stops, ", ", fn {why, n} -> "#{why} ×#{n}" end)
    )
  end

  # ROBOT command 0114 ended ERROR INTERRUPTED BY PARTITION RESTART → ROBOT ERROR INTERRUPTED …
  defp stop_reason(%{stopped: nil}), do: "nothing (completed)"

  defp stop_reason(%{stopped: %{reason: reason}}),
    do: String.replace(reason, ~r/ command \d{4} ended/, "")

  ## The WC

  defp cycles(client, script, ws, acc) do
    receive do
      :stop -> Enum.reverse(acc)
    after
      0 ->
        clear(client, ws)
        cycles(client, script, ws, [run_cycle(client, script) | acc])
    end
  end

  defp run_cycle(client, script),
    do: Runner.run(client, script, timeout: @command_ms, poll_interval: 10, expect_grace: 2_000)

  # What an operator does between cycles: the machine left to finish, the robot sent home, the
  # leases given back, the gripper opened, and the part put back in tray #1. Each step may fail
  # (something is being killed): the cycle then stops early, and the next clear tries again.
  @clear [
    "WAIT MONARCH IDLE",
    "M RELEASE_TABLE",
    "R DO MOVE SAFE",
    "R RELEASE_TABLE",
    "R RELEASE_TRAY1",
    "F RELEASE_TABLE",
    "G OPEN"
  ]

  defp clear(client, ws) do
    results =
      for line <- @clear do
        {:ok, step} = Script.parse(line)
        run_cycle(client, step).result
      end

    plant = Floor.plant(ws)
    :ok = Plant.set_part(plant, :gripper, false)
    :ok = Plant.set_part(plant, :vise, false)
    :ok = Plant.set_part(plant, :tray1, true)
    Enum.all?(results, &(&1 == :completed))
  end

  # After the campaign: every process back and every link up, then the cell cleared.
  defp settle(ws, client) do
    assert eventually(fn -> Enum.all?(@partitions, &(Partition.whereis(ws, &1) != nil)) end)

    assert eventually(
             fn ->
               safe(fn ->
                 elem(Vws.Links.VAL.info(WS.whereis(ws, :val)).state, 0) != :down and
                   Vws.Links.DNC.info(WS.whereis(ws, :ge2000)).state == :idle and
                   Vws.Links.HPIB.info({ws, 9}).state in [:ready, :busy] and
                   Vws.Links.HPIB.info({ws, 8}).state in [:ready, :busy]
               end)
             end,
             20_000,
             50
           )

    assert eventually(fn -> clear(client, ws) end, 60_000, 100)
  end

  ## The killers

  # One killer per supervisor, side by side, each with its own schedule from @seed: every
  # target @kills times, shuffled, with random gaps.
  defp campaign(ws, events, {group, groups}) do
    # the VAL II wire is one process (`:val`, DDCMP run inside it): killing it kills both layers
    links = for {id, _pid, _, _} <- Supervisor.which_children(WS.whereis(ws, :links)), do: id
    share = fn all -> all |> Enum.sort() |> Enum.drop(group) |> Enum.take_every(groups) end

    [
      {1, Enum.map(share.(links), &{:links, &1})},
      {2, Enum.map(share.(@partitions), &{:partitions, &1})}
    ]
    |> Enum.map(fn {n, targets} ->
      Task.async(fn -> killer(ws, events, {n, group}, targets) end)
    end)
    |> Enum.flat_map(&Task.await(&1, :infinity))
    |> Enum.sort()
  end

  defp killer(ws, events, {n, group}, targets) do
    {a, b, c} = @seed
    :rand.seed(:exsss, {a, b, c + n + 10 * group})
    schedule = targets |> Enum.flat_map(&List.duplicate(&1, @kills)) |> Enum.shuffle()
    gaps = Enum.map(schedule, fn _ -> Enum.random(@gap) end)

    {kills, _window, _last} =
      Enum.zip(schedule, gaps)
      |> Enum.reduce({[], [], %{}}, fn {target, gap}, {kills, window, last} ->
        Process.sleep(gap)
        window = wait_window(window)
        pid = alive(ws, target, last[target])
        # the kill's time is its death's: what the process finished while the signal was on its
        # way was finished before the kill
        ref = Process.monitor(pid)
        Process.exit(pid, :kill)
        assert_receive {:DOWN, ^ref, :process, ^pid, _}, 5_000
        at = System.monotonic_time()
        :ets.insert(events, {{at, System.unique_integer([:monotonic])}, :kill, target, pid})
        {[{at, target, pid} | kills], [now() | window], Map.put(last, target, pid)}
      end)

    kills
  end

  # The supervisor counts its restarts in whole seconds: a window of @window_ms + 1 s here.
  defp wait_window(window) do
    recent = Enum.filter(window, &(&1 > now() - @window_ms - 1_000))

    if length(recent) >= @per_window do
      Process.sleep(Enum.min(recent) + @window_ms + 1_000 - now() + 1)
      wait_window(window)
    else
      recent
    end
  end

  # The target's pid once it is running again (never the one killed before).
  defp alive(ws, target, killed) do
    pid_of = fn ->
      case pid(ws, target) do
        pid when is_pid(pid) and pid != killed -> if Process.alive?(pid), do: pid
        _ -> nil
      end
    end

    assert eventually(fn -> pid_of.() != nil end, 10_000, 5),
           "#{inspect(target)} did not come back"

    pid_of.()
  end

  defp pid(ws, {:partitions, p}), do: Partition.whereis(ws, p)

  defp pid(ws, {:links, id}) do
    Enum.find_value(Supervisor.which_children(WS.whereis(ws, :links)), fn
      {^id, pid, _, _} when is_pid(pid) -> pid
      _ -> nil
    end)
  end

  # nil when a process asked is not there (restarting)
  defp safe(fun) do
    fun.()
  rescue
    _ -> nil
  catch
    :exit, _ -> nil
  end

  ## What happened

  # Every event of the workstation, in an ETS table: {{monotonic, unique}, kind, a, b}.
  @doc false
  def record(ws) do
    table = :ets.new(:crash_events, [:ordered_set, :public])
    id = {__MODULE__, ws}
    {daq2_bus, _address} = HydraulicController.daq2_device(Floor.hydraulic_controller(ws))

    :ok =
      Vws.Telemetry.attach_many(
        id,
        [
          [:vws, :partition, :command_dispatched],
          [:vws, :partition, :command, :start],
          [:vws, :partition, :command_finished],
          [:vws, :sim, :plant, :actuator],
          [:vws, :sim, :val2, :command],
          [:vws, :sim, :ge2000, :command],
          [:vws, :hpib, :retry],
          [:vws, :hydraulic_controller, :relay_corrected]
        ],
        fn event, _measurements, meta, _ ->
          # (an HPIB device of the workstation names it as its bus — DAQ #1's; the hydraulic
          # controller's DAQ #2 is on the controller's own bus, and its tries of a relay write
          # are the bus's too: before, they were not recorded, and a write DAQ #2's device sent
          # again after a late answer counted as the command run twice)
          # (the controller's corrections of DAQ #2's relays name its device, {bus, address})
          bus_daq =
            cond do
              meta[:bus] == ws -> :daq1
              meta[:bus] == daq2_bus -> :daq2
              match?({^daq2_bus, _}, meta[:device]) -> :daq2
              true -> nil
            end

          if meta[:workstation] == ws or bus_daq != nil do
            key = {System.monotonic_time(), System.unique_integer([:monotonic])}
            :ets.insert(table, entry(key, event, Map.put(meta, :bus_daq, bus_daq)))
          end
        end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
    table
  end

  defp entry(key, [:vws, :partition, :command_dispatched], m),
    do: {key, :dispatched, {m.partition, m.command}, m.text}

  # The command's worker runs the handler: its links name the partition process that started it.
  defp entry(key, [:vws, :partition, :command, :start], m) do
    {:links, links} = Process.info(self(), :links)
    {key, :started, {m.partition, m.command}, links}
  end

  defp entry(key, [:vws, :partition, :command_finished], m),
    do: {key, :finished, {m.partition, m.command}, m.status}

  defp entry(key, [:vws, :sim, :plant, :actuator], m),
    do: {key, :executed, {:relay, m.signal, m.action}, {m.daq, m.channel}}

  defp entry(key, [:vws, :sim, :val2, :command], m),
    do: {key, :executed, {:val2, m.text}, nil}

  defp entry(key, [:vws, :hpib, :retry], m),
    do: {key, :retried, m.commands, m.bus_daq}

  # the hydraulic controller found DAQ #2's relays not as it wrote them and writes them again:
  # in the story, not excused (the event does not say which relays)
  defp entry(key, [:vws, :hydraulic_controller, :relay_corrected], m),
    do: {key, :corrected, m.device, m.bus_daq}

  defp entry(key, [:vws, :sim, :ge2000, :command], m),
    do: {key, :executed, {:ge2000, m.operation}, m.name}

  @doc """
  The campaign's judgement of a run's events (an ETS table of `{key, kind, a, b}` rows, as
  `record/1` keeps them) and kills: raises with every problem found, else the figures. Public for
  the tests of the judgement itself (`crash_campaign_check_test.exs`).
  """
  def check(events, kills) do
    rows = :ets.tab2list(events)
    dispatched = for {key, :dispatched, id, text} <- rows, do: {key, id, text}

    finished =
      Enum.group_by(
        for({key, :finished, id, status} <- rows, do: {id, {key, status}}),
        &elem(&1, 0),
        &elem(&1, 1)
      )

    # each command dispatched once, and ended once, DONE or ERROR with a reason
    twice_dispatched =
      for {id, n} <- Enum.frequencies_by(dispatched, &elem(&1, 1)),
          n > 1,
          do: "#{inspect(id)} dispatched #{n} times"

    bad_ends =
      for {_key, id, text} <- dispatched,
          ends = Map.get(finished, id, []),
          not match?([{_, :done}], ends) and not match?([{_, {:error, <<_, _::binary>>}}], ends),
          do: "#{inspect(id)} #{text} ended #{inspect(Enum.map(ends, &elem(&1, 1)))}"

    # a command in flight in a partition when it was killed ended ERROR: one the killed process
    # had started, or one dispatched before the kill that no process started (the restarted
    # partition ends it). One dispatched while the kill's DOWN was on its way to this test and
    # started by the restarted partition was never in the killed one.
    started = Map.new(for {_key, :started, id, links} <- rows, do: {id, links})

    interrupted =
      for {at, {:partitions, p}, pid} <- kills,
          {{t, _}, {^p, _} = id, _text} <- dispatched,
          t < at,
          pid in Map.get(started, id, [pid]),
          {{f, _}, status} <- Map.get(finished, id, []),
          f > at,
          do: {id, status}

    not_error =
      for {id, status} <- interrupted,
          not match?({:error, _}, status),
          uniq: true,
          do: "#{inspect(id)} was in flight in its killed partition but ended #{inspect(status)}"

    # at most once on the equipment
    kinds =
      for {key, id, text} <- dispatched, kind = kind(id, text), kind != nil, do: {key, id, kind}

    executed = for {key, :executed, kind, _} <- rows, physical?(kind), do: {key, kind}

    attributed =
      Enum.reduce(executed, %{}, fn {key, kind}, acc ->
        case Enum.filter(kinds, fn {k, _id, kd} -> kd == kind and k < key end) |> List.last() do
          nil -> Map.update(acc, {:nobody, kind}, 1, &(&1 + 1))
          {_, id, _} -> Map.update(acc, id, 1, &(&1 + 1))
        end
      end)

    # A relay write is repeatable (it sets a state): the HPIB device sends it again when its
    # answer is late or damaged (`[:vws, :hpib, :retry]`), and a late try may reach the DAQ too.
    # Such an execution is the bus's try of the same write, not the command run again: as many
    # executions beyond the first as the bus retried that write while the command was the latest
    # of its kind are not counted against it — a write to the same DAQ's same channel (DAQ #1 on
    # the workstation's bus, DAQ #2 on the hydraulic controller's).
    {attributed, bus_retried} = discount_bus_retries(attributed, kinds, rows)

    unattributed =
      for {{:nobody, kind}, n} <- attributed, do: "#{inspect(kind)} ran #{n} times, no command"

    twice_ids = for {id, n} <- attributed, n > 1, do: id
    twice_run = for {id, n} <- attributed, n > 1, do: "#{inspect(id)} ran #{n} times"

    # DONE ran it once — or, a relay write, found it done: a write lost with its HPIB connection
    # is tried again as a read (never written blindly), and a relay already in the commanded
    # state (the same write last, an OPEN after the operator's OPEN) is DONE with no write
    not_run_ids =
      for {key, id, kind} <- kinds,
          match?([{_, :done}], finished[id]),
          Map.get(attributed, id) != 1,
          not already_so?(rows, key, kind, Map.get(attributed, id, 0)),
          do: id

    not_run =
      for {_key, id, kind} <- kinds,
          id in not_run_ids,
          do: "#{inspect(id)} DONE but #{inspect(kind)} ran #{Map.get(attributed, id, 0)} times"

    problems = twice_dispatched ++ bad_ends ++ not_error ++ unattributed ++ twice_run ++ not_run

    assert problems == [],
           Enum.join(problems, "\n") <>
             "\n\n" <> story(rows, Enum.uniq(twice_ids ++ not_run_ids), kinds)

    %{
      bus_retried: bus_retried,
      dispatched: length(dispatched),
      interrupted: length(Enum.uniq_by(interrupted, &elem(&1, 0))),
      executed: length(executed)
    }
  end

  # A relay write not run for a command whose relay was already so when it was dispatched: the
  # last write to that relay before it set the same state.
  defp already_so?(rows, dispatched_at, {:relay, signal, action}, 0) do
    last =
      for {key, :executed, {:relay, ^signal, a}, _} <- rows, key < dispatched_at do
        {key, a}
      end
      |> Enum.max_by(&elem(&1, 0), fn -> nil end)

    match?({_, ^action}, last)
  end

  defp already_so?(_rows, _dispatched_at, _kind, _runs), do: false

  defp discount_bus_retries(attributed, kinds, rows) do
    channel = Map.new(for {_, :executed, {:relay, sig, _}, ch} <- rows, do: {sig, ch})

    retries =
      for {key, :retried, commands, daq} <- rows,
          {op, channels} <- commands,
          op in [:rout_clos, :rout_open],
          c <- channels,
          do: {key, {daq, c}, if(op == :rout_clos, do: :close, else: :open)}

    Enum.reduce(attributed, {attributed, 0}, fn
      {id, n}, {acc, total} when n > 1 ->
        case Enum.find(kinds, fn {_key, i, _kind} -> i == id end) do
          {from, ^id, {:relay, signal, action} = kind} ->
            until =
              Enum.find_value(kinds, :end, fn {k, i, kd} ->
                kd == kind and k > from and i != id and k
              end)

            tries =
              Enum.count(retries, fn {k, c, a} ->
                k > from and (until == :end or k < until) and c == channel[signal] and
                  a == action
              end)

            excused = min(n - 1, tries)
            {Map.put(acc, id, n - excused), total + excused}

          _ ->
            {acc, total}
        end

      _, acc ->
        acc
    end)
  end

  # What happened around each command that ran twice (or not once): every event of the
  # workstation (dispatches, starts, ends, physical executions, kills) from a second before its
  # dispatch to a second after the next command of its kind, in order, with ms from the first.
  defp story(_rows, [], _kinds), do: ""

  defp story(rows, ids, kinds) do
    rows = Enum.sort(rows)
    t0 = rows |> List.first() |> elem(0) |> elem(0)
    ms = &System.convert_time_unit(&1 - t0, :native, :millisecond)
    second = System.convert_time_unit(1, :second, :native)

    Enum.map_join(Enum.take(ids, 3), "\n\n", fn id ->
      {{from, _}, _, kind} = Enum.find(kinds, fn {_key, i, _kind} -> i == id end)

      until =
        case Enum.find(kinds, fn {{t, _}, i, k} -> k == kind and t > from and i != id end) do
          {{t, _}, _, _} -> t
          nil -> from + 3 * second
        end

      window =
        for {{t, _}, _, _, _} = row <- rows, t >= from - second, t <= until + second, do: row

      line = fn {{t, _}, what, a, b} ->
        b = if what == :started, do: :links, else: b
        "#{ms.(t)} ms #{what} #{inspect(a)} #{inspect(b, limit: 5)}"
      end

      # first what bears on it (the command, the executions of its kind, the bus's tries, the
      # hydraulic controller's relay corrections, the kills), then everything: a CI page keeps
      # the first lines of a failure
      relevant =
        for {{t, _}, what, a, _} = row <- window,
            a == id or (what == :executed and a == kind) or
              (what in [:retried, :corrected, :kill] and t >= from),
            do: line.(row)

      "#{inspect(id)} (#{inspect(kind)}), what bears on it:\n" <>
        Enum.join(Enum.take(relevant, 100), "\n") <>
        "\n\n#{inspect(id)}, every event around it:\n" <>
        Enum.map_join(Enum.take(window, 300), "\n", line)
    end)
  end

  # Per partition, its last command to finish and how: {number, :done | {:error, reason}}.
  defp last_finished(events) do
    for {_key, :finished, {partition, number}, status} <- :ets.tab2list(events),
        into: %{},
        do: {partition, {number, status}}
  end

  # What a command does on the equipment, as the simulators report it (nil: nothing physical).
  defp kind({:robot, _}, text) do
    case Vws.Codecs.Commands.parse(:robot, text) do
      {:ok, {:do, _, _} = c} -> {:val2, Vws.Partitions.Robot.instruction(c)}
      {:ok, {:do, _, _, _} = c} -> {:val2, Vws.Partitions.Robot.instruction(c)}
      {:ok, {:disable_tray, 1}} -> {:relay, :tray1_lock, :close}
      {:ok, {:release_tray, 1}} -> {:relay, :tray1_lock, :open}
      _ -> nil
    end
  end

  defp kind({:gripper, _}, "OPEN"), do: {:relay, :gripper_open_solenoid, :close}
  defp kind({:gripper, _}, "CLOSE"), do: {:relay, :gripper_close_solenoid, :close}
  defp kind({:fixture, _}, "OPEN"), do: {:relay, :vise_open_valve, :close}
  defp kind({:fixture, _}, "CLOSE"), do: {:relay, :vise_close_valve, :close}
  defp kind({:monarch, _}, "CYCLE_START"), do: {:relay, :cycle_start_relay, :close}
  defp kind({:monarch, _}, "DOWNLOAD_GE"), do: {:ge2000, :part_program}
  defp kind({:monarch, _}, "PROGRAM_SELECT" <> _), do: {:ge2000, :remote_control}
  defp kind({:hydraulic, _}, "CLAMP_PALLET"), do: {:relay, :ram_x_valve, :close}
  defp kind(_id, _text), do: nil

  # The executions that are some command's (other relay writes: a valve switched off after a
  # failed vise command, the pallet's later steps, the cycle-start button let go, …).
  @relays [
    {:relay, :tray1_lock, :close},
    {:relay, :tray1_lock, :open},
    {:relay, :gripper_open_solenoid, :close},
    {:relay, :gripper_close_solenoid, :close},
    {:relay, :vise_open_valve, :close},
    {:relay, :vise_close_valve, :close},
    {:relay, :cycle_start_relay, :close},
    {:relay, :ram_x_valve, :close}
  ]

  # (WHERE asks where the arm is: it moves nothing)
  defp physical?({:val2, "WHERE"}), do: false
  defp physical?({:val2, _text}), do: true
  defp physical?({:ge2000, op}), do: op in [:part_program, :remote_control]
  defp physical?(relay), do: relay in @relays

  defp now, do: System.monotonic_time(:millisecond)
end
