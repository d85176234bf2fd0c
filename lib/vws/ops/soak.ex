defmodule Vws.Ops.Soak do
  @moduledoc """
  The machining cycle run over and over on a simulated floor whose every link — the WC's, the
  VAL II's (DDCMP), the GE-2000's (DNC), DAQ #1's and the hydraulic controller's (HPIB), and the
  hydraulic controller's own to DAQ #2 — goes through a faulty line (`Vws.Sim.Line`, seeded), and
  each cycle audited:

    * **completed** — the WC's script ran to its end (`Vws.Peers.WC.Runner`);
    * **retries** — every try again, from telemetry, by kind: WC strings and program lines sent
      again, program transfers made again, strings SUN_COMM recognised as retransmissions,
      DDCMP retransmissions, DNC retries (NAK, ENQ, …), HPIB requests tried again, relays set
      again;
    * **commands** — the commands the WC numbered under the faults (status queries apart);
    * **lost** — commands the WC numbered that never ended (no `DONE`/`ERROR` in the CEC);
    * **duplicated** — commands that started (or ended) more than once in the CEC, and equipment
      that did more than a clean cycle does: VAL II commands received and GE-2000 machining
      cycles per cycle, against the first cycle run without faults;
    * **silent differences** (issue 15) — what ended `DONE` but is not what was sent: after each
      cycle the CEC's NC file, the GE-2000's copy of the program and NC_UP are compared byte for
      byte with the script's program (the cycle ends with `M UPLOAD_GE` and `UPLOAD`, added to
      the script by the soak, so a program goes WC → CEC → GE-2000 → CEC → WC every cycle), and
      the relays of every slot with those at the end of the clean cycle. A store only happens on
      `DONE`, so any difference there is one; in a completed cycle every comparison counts, in a
      stopped one those whose command may not have run are left out. Must be 0.

  A cycle that stops leaves the floor where it stopped: the part in the gripper or the vise, the
  arm in a work volume, leases held. Before the next cycle the soak does what an operator would
  (`priv/sims/recover.vws`'s header): it runs the recovery script, the lines clean for it, and
  puts the blank back in tray #1 by hand. Each cycle after a stop then measures the faults, not
  the stop before it. A recovery that stops too ends the soak (`unrecovered`).

  `bench/soak.exs` prints the figures of a long run; the reliability tests run a short one.

      report = Vws.Ops.Soak.run(cycles: 3, ber: 1.0e-4, seed: 1, time_scale: 20)
      report.completed  #=> 3
      report.lost       #=> 0
  """

  alias Vws.Sim.{Floor, GE2000, Line, VAL2}
  alias Vws.Peers.WC.{Client, Runner, Script}

  @links [:wc, :robot, :ge2000, :daq1, :hydraulic, :daq2]
  # how long a recovery waits for the stopped cycle's commands to end (the cycle script's own
  # longest TIMEOUT, a machining cycle's)
  @recover_wait_ms 900_000
  @retry_events [
    {[:vws, :sun_comm, :retransmission], :sun_comm_retransmissions},
    {[:vws, :ddcmp, :retransmission], :ddcmp_retransmissions},
    {[:vws, :dnc, :retry], :dnc_retries},
    {[:vws, :monarch, :request_again], :dnc_requests_made_again},
    {[:vws, :hpib, :retry], :hpib_retries},
    {[:vws, :vws_status, :actuation_retry], :relays_set_again}
  ]
  @command_events [
    {[:vws, :partition, :command, :start], :started},
    {[:vws, :partition, :command_finished], :finished}
  ]

  @type report :: %{
          workstation: String.t(),
          cycles: non_neg_integer,
          completed: non_neg_integer,
          commands: non_neg_integer,
          stopped: [{pos_integer, String.t()}],
          retries: %{atom => non_neg_integer},
          lost: non_neg_integer,
          lost_commands: [{atom, pos_integer}],
          duplicated: non_neg_integer,
          duplicates: [
            {:started | :finished, atom, pos_integer, pos_integer}
            | {:equipment, pos_integer, keyword}
          ],
          silent_differences: non_neg_integer,
          silent: [{pos_integer, term}],
          bits_flipped: %{atom => non_neg_integer},
          elapsed_ms: non_neg_integer,
          recovered: [pos_integer],
          unrecovered: nil | {pos_integer, String.t()}
        }

  @doc """
  Starts the floor and the workstation (linked to the caller), runs one clean cycle as the
  reference, then `:cycles` cycles under the faults, and returns the report. Options: `:cycles`
  (default 100), `:ber` (1.0e-4), `:faults` (more `Vws.Sim.Line` faults for every link),
  `:links` (the links that get the faults, default all: `#{inspect(@links)}`), `:seed` (0),
  `:time_scale` (20), `:id`, `:script` (default the shipped machining cycle), `:recover` (the
  script run after a stopped cycle, default the shipped `priv/sims/recover.vws`),
  `:timeout` (ms a command may take, 60 000), `:on_cycle` — called with `(n, summary)` after each.
  The floor and the workstation are stopped at the end.
  """
  @spec run(keyword) :: report
  def run(opts \\ []) do
    id = Keyword.get(opts, :id, "SOAK-#{System.unique_integer([:positive])}")
    cycles = Keyword.get(opts, :cycles, 100)
    faults = [ber: Keyword.get(opts, :ber, 1.0e-4)] ++ Keyword.get(opts, :faults, [])
    path = Keyword.get_lazy(opts, :script, &Vws.Ops.Demo.default_script/0)
    {:ok, script} = Script.parse_file(path)

    {:ok, recover_script} =
      Script.parse_file(
        Keyword.get_lazy(opts, :recover, fn -> Vws.Ops.Demo.sims_script("recover.vws") end)
      )

    {script, program} = with_round_trip(script)
    runner_opts = [timeout: Keyword.get(opts, :timeout, 60_000)]
    on_cycle = Keyword.get(opts, :on_cycle, fn _n, _summary -> :ok end)
    links = Keyword.get(opts, :links, @links)

    counts = :ets.new(:soak_counts, [:public, :set])
    handler = {__MODULE__, id}
    :ok = attach(handler, id, counts)

    {:ok, floor} =
      Vws.Ops.Demo.start_shop_floor(
        id: id,
        time_scale: Keyword.get(opts, :time_scale, 20),
        lines: [faults: [], seed: Keyword.get(opts, :seed, 0)]
      )

    try do
      {:ok, client} = Client.connect(floor.wc)
      clean = run_cycle(client, script, runner_opts, id)

      if clean.summary.result != :completed,
        do: raise("the clean reference cycle stopped: #{clean.summary.stopped.reason}")

      clean = Map.put(clean, :relays, relays(id))
      {[], []} = audit(id, clean, clean, program)

      # the numbers the WC gives out from here on are the audited ones
      clean = Map.put(clean, :next_numbers, Client.info(client).next_numbers)
      :ets.delete_all_objects(counts)

      faulty = fn faults ->
        for {link, line} <- Floor.lines(id),
            link in links,
            do: :ok = Line.set_faults(line, :both, faults)
      end

      faulty.(faults)
      t0 = System.monotonic_time(:millisecond)

      {results, recovered, unrecovered} =
        Enum.reduce_while(1..cycles//1, {[], [], nil}, fn n, {results, recovered, nil} ->
          result = run_cycle(client, script, runner_opts, id)
          {silent, _unverified} = audit(id, result, clean, program)
          on_cycle.(n, result.summary)
          results = [Map.put(result, :silent, silent) | results]

          if result.summary.result == :completed or n == cycles do
            {:cont, {results, recovered, nil}}
          else
            case recover(client, recover_script, runner_opts, id, faulty, faults) do
              :ok -> {:cont, {results, recovered ++ [n], nil}}
              why -> {:halt, {results, recovered, {n, why}}}
            end
          end
        end)

      elapsed = System.monotonic_time(:millisecond) - t0

      report(id, client, clean, Enum.reverse(results), counts, elapsed)
      |> Map.merge(%{recovered: recovered, unrecovered: unrecovered})
    after
      Vws.Telemetry.detach(handler)
      Vws.CEC.Workstation.stop(id)
      stop_floor(id)
    end
  end

  # After a stopped cycle, what an operator does before the next one (priv/sims/recover.vws's
  # header): the arm to SAFE and every lease given up, by the recovery script, with the lines
  # clean (the recovery is not what is measured), then the blank put back in tray #1 by hand.
  # `:ok`, or why the floor could not be recovered (the soak ends there: a cycle after it
  # would only measure where the stopped one left the floor).
  defp recover(client, script, runner_opts, id, faulty, faults) do
    # the damaging faults off (Line.set_faults/3 keeps what it is not told); a line's pacing
    # and delays stay as they are
    faulty.(ber: 0.0, drop: 0.0, disconnect_after: nil, disconnect_rate: 0.0)

    # a command of the stopped cycle may still run (the WC gave up on a status query, not on
    # the command): the operator waits for it to end, as the script waits for the machine
    result =
      with :ok <- commands_ended(id, System.monotonic_time(:millisecond) + @recover_wait_ms) do
        summary = Runner.run(client, script, runner_opts)

        if summary.result == :completed,
          do: :ok,
          else: "the recovery stopped: #{summary.stopped.reason}"
      end

    faulty.(faults)

    with :ok <- result do
      plant = Floor.plant(id)

      for where <- [:gripper, :vise, :tray2],
          do: :ok = Vws.Sim.Plant.set_part(plant, where, false)

      :ok = Vws.Sim.Plant.set_part(plant, :tray1, true)
    end
  end

  defp commands_ended(id, deadline) do
    in_flight =
      for p <- Vws.CEC.Mailbox.partitions(),
          n = Vws.CEC.Mailbox.in_flight(id, p),
          do: {p, n}

    cond do
      in_flight == [] ->
        :ok

      System.monotonic_time(:millisecond) > deadline ->
        "commands still running after #{div(@recover_wait_ms, 1000)} s: #{inspect(in_flight)}"

      true ->
        Process.sleep(100)
        commands_ended(id, deadline)
    end
  end

  # the floor's supervisor (its lines are its children), then the WC's line of Vws.Ops.Demo
  defp stop_floor(id) do
    for name <- [Vws.Names.via(id, :sim_floor), Floor.line(id, :wc)],
        pid = GenServer.whereis(name),
        do: GenServer.stop(pid)
  end

  defp run_cycle(client, script, runner_opts, id) do
    robot0 = length(VAL2.info(Floor.robot(id)).commands)
    machined0 = GE2000.state(Floor.ge2000(id)).cycles
    summary = Runner.run(client, script, runner_opts)

    %{
      summary: summary,
      robot_commands: length(VAL2.info(Floor.robot(id)).commands) - robot0,
      machined: GE2000.state(Floor.ge2000(id)).cycles - machined0
    }
  end

  defp report(id, client, clean, results, counts, elapsed) do
    completed = Enum.filter(results, &(&1.summary.result == :completed))
    rows = :ets.tab2list(counts)
    count = fn key -> Enum.sum(for {{^key, _, _}, n} <- rows, do: n) end

    # every command number the WC gave out under the faults (status queries apart) must have
    # ended exactly once
    used =
      for {letter, next} <- Client.info(client).next_numbers,
          letter != "S",
          number <- Map.get(clean.next_numbers, letter, 1)..(next - 1)//1,
          do: {partition(letter), number}

    finished = for {{:finished, p, n}, c} <- rows, into: %{}, do: {{p, n}, c}
    started = for {{:started, p, n}, c} <- rows, into: %{}, do: {{p, n}, c}
    lost = Enum.filter(used, &(Map.get(finished, &1, 0) == 0))

    twice =
      for {what, seen} <- [started: started, finished: finished],
          {{p, n}, c} <- Enum.sort(seen),
          c > 1,
          do: {what, p, n, c}

    # equipment that did more than a clean cycle does, in a completed cycle
    extra =
      for {r, n} <- Enum.with_index(results, 1),
          r.summary.result == :completed,
          robot = max(r.robot_commands - clean.robot_commands, 0),
          machined = max(r.machined - clean.machined, 0),
          robot + machined > 0,
          do: {:equipment, n, robot: robot, machined: machined}

    summaries = Enum.map(results, & &1.summary)

    stopped =
      for {r, n} <- Enum.with_index(results, 1),
          r.summary.result != :completed,
          do: {n, r.summary.stopped.reason}

    %{
      workstation: id,
      cycles: length(results),
      completed: length(completed),
      commands: length(used),
      stopped: stopped,
      retries:
        Map.merge(
          Map.new(@retry_events, fn {_event, key} -> {key, count.(key)} end),
          %{
            wc_resends: Enum.sum(Enum.map(summaries, & &1.resends)),
            transfers_made_again: Enum.sum(Enum.map(summaries, & &1.transfers_broken))
          }
        ),
      lost: length(lost),
      lost_commands: lost,
      duplicated:
        length(twice) +
          Enum.sum(for {:equipment, _, extra} <- extra, do: extra[:robot] + extra[:machined]),
      duplicates: twice ++ extra,
      silent_differences: Enum.sum(Enum.map(results, &length(&1.silent))),
      silent: for({r, n} <- Enum.with_index(results, 1), d <- r.silent, do: {n, d}),
      bits_flipped:
        Map.new(Floor.lines(id), fn {link, line} ->
          info = Line.info(line)
          {link, info.to_target.bits_flipped + info.to_client.bits_flipped}
        end),
      elapsed_ms: elapsed
    }
  end

  # The script and its program, the round trip back to the WC added at its end: the GE-2000's
  # copy into NC_UP, NC_UP to the WC.
  defp with_round_trip(script) do
    case for(%{op: {:download, _path, lines}} <- script.steps, do: lines) do
      [] ->
        {script, nil}

      [lines | _] ->
        {:ok, file} = Vws.Links.DNC.Program.file_name(lines)
        {:ok, extra} = Script.parse("M UPLOAD_GE(#{file})\nUPLOAD\n")
        {%{script | steps: script.steps ++ extra.steps}, %{lines: lines, file: file}}
    end
  end

  defp relays(id) do
    Vws.Sim.Plant.snapshot(Floor.plant(id)).relays |> Enum.sort()
  end

  # What ended DONE must be what was sent: `{silent_differences, comparisons_left_out}`.
  defp audit(_id, _result, _clean, nil), do: {[], []}

  defp audit(id, result, clean, program) do
    ws = id
    completed? = result.summary.result == :completed
    text = Vws.Links.DNC.Program.to_text(program.lines)
    nc_file = Vws.CEC.Mailbox.nc_file(ws)
    nc_up = Vws.CEC.Mailbox.nc_up(ws)
    ge = GE2000.program(Floor.ge2000(id), program.file)
    uploads = result.summary.uploads

    checks = [
      # stored only on DONE: whatever is there must be the program, cycle completed or not
      {:nc_file, nc_file in [[], program.lines], true},
      {:nc_up, nc_up in [[], program.lines], true},
      # the GE-2000 files any whole program; MONARCH's DONE vouches for it in a completed cycle
      {:ge2000_file, ge == text, completed?},
      # what the WC took from UPLOAD_SUN
      {:uploaded, Enum.all?(uploads, &(&1 == program.lines)), completed? or uploads != []},
      {:uploads_done, length(uploads) == 1, completed?},
      # every relay where the clean cycle left it
      {:relays, relays(id) == clean.relays, completed?}
    ]

    silent = for {what, ok?, counts?} <- checks, counts? and not ok?, do: {what, detail(what, id)}

    {silent, for({what, _, false} <- checks, do: what)}
  end

  defp detail(:relays, id), do: relays(id)
  defp detail(_what, _id), do: nil

  defp partition("R"), do: :robot
  defp partition("M"), do: :monarch
  defp partition("G"), do: :gripper
  defp partition("F"), do: :fixture
  defp partition("V"), do: :vacuum
  defp partition("H"), do: :hydraulic

  defp attach(handler, id, counts) do
    events = Enum.map(@retry_events ++ @command_events, &elem(&1, 0))
    keys = Map.new(@retry_events ++ @command_events)

    Vws.Telemetry.attach_many(
      handler,
      events,
      fn event, measurements, metadata, _ ->
        if ours?(metadata, id) do
          case keys[event] do
            key when key in [:started, :finished] ->
              :ets.update_counter(
                counts,
                {key, metadata.partition, metadata.command},
                1,
                {nil, 0}
              )

            key ->
              n = Map.get(measurements, :count, 1)
              :ets.update_counter(counts, {key, nil, nil}, n, {nil, 0})
          end
        end
      end,
      nil
    )
  end

  # The CEC's side of the floor: the workstation's own events, its HPIB bus, and the hydraulic
  # controller's bus to DAQ #2.
  defp ours?(%{workstation: ws}, id), do: ws == id

  defp ours?(%{bus: bus}, id),
    do: bus == id or bus == {:hydraulic_controller, Floor.hydraulic_controller(id)}

  defp ours?(_metadata, _id), do: false
end
