# How many workstations one node sustains, and what each costs in memory.
#
#     mix run bench/scale.exs [--floor sim|obedient] [--counts 10,25,50,100] [--seconds 20]
#                             [--time-scale 20] [--all]
#
# For each count N (ascending) it starts N workstations, each on loopback endpoints only (no
# socket anywhere), connects one WC (`Vws.Peers.WC.Client`) to each and lets every WC run its cycle
# script again and again for --seconds; then it stops them all and goes on to the next N, unless
# a cycle failed (--all goes on anyway).
#
#   --floor sim (default): each workstation has its whole simulated shop floor, as `mix vws.demo`
#     has (`Vws.Sim.Floor`): the plant with DAQ #1 (HPIB; VWS_STATUS polls it every 20 ms as in
#     the seed), DAQ #2 and the hydraulic controller (HPIB), the GE-2000 (DNC), the VAL II
#     (DDCMP + VAL) and the material-handling system, time-scaled by --time-scale, a blank in
#     tray #1 — and every partition linked to its device. Each WC runs the shipped machining
#     cycle (`priv/sims/machining_cycle.vws`: the blank into the vise, the NC program downloaded,
#     sent to the GE-2000 and run, the part back into tray #1), which leaves the floor as it
#     found it, so it can run again.
#   --floor obedient: the six command partitions end every command DONE after --command-ms
#     (default 300) and VWS_STATUS has no DAQ: the WC link, SUN_COMM, the mailboxes and the
#     partitions' processes alone.
#
# Memory per workstation, in MB: "CEC" is what the workstation itself holds — every process of
# its supervision tree and the processes they started linked (the VAL II's DDCMP link, SUN_COMM's
# acceptor, command tasks), with their heaps and mailboxes, and the ETS tables they own (the
# mailboxes) — summed after a garbage collection, once every WC is connected, the average over
# the N workstations, and its largest value during the run (sampled once, half-way, without a
# garbage collection). "all" is the growth of :erlang.memory(:total) over the whole step
# (simulators, workstations, WC clients, loopback pairs, binaries) divided by N, at its highest
# (sampled every 500 ms while the cycles run). Target: 1,000 workstations on this 2-core
# machine, under 2 MB of CEC memory each, every cycle completing.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench
alias Vws.Partitions.VwsStatus
alias Vws.Peers.WC.{Client, Runner, Script}

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [
      floor: :string,
      counts: :string,
      seconds: :integer,
      time_scale: :float,
      command_ms: :integer,
      all: :boolean
    ]
  )

floor = Keyword.get(opts, :floor, "sim")
seconds = Keyword.get(opts, :seconds, 20)
scale = Keyword.get(opts, :time_scale, 20.0)
command_ms = Keyword.get(opts, :command_ms, 300)

default_counts = if floor == "sim", do: "10,25,50,100,200", else: "100,250,500,1000"

counts =
  opts
  |> Keyword.get(:counts, default_counts)
  |> String.split(",")
  |> Enum.map(&String.to_integer/1)

defmodule Bench.Obedient do
  @moduledoc false
  # A partition that takes any command and ends it DONE at once.
  @behaviour Vws.CEC.Partition.CommandSet
  @impl true
  def device, do: "NOTHING"
  @impl true
  def parse(text), do: {:ok, text}
  @impl true
  def execute(_command, ctx) do
    Process.sleep(ctx.options[:ms] || 0)
    :done
  end
end

obedient_cycle = """
R DO MOVE SAFE & G OPEN
F OPEN
V ON
H CLAMP_PALLET
M PROGRAM_SELECT(001234)
STATUS VISE
R DO MOVE TRAY1 & G CLOSE
F CLOSE
V OFF
R DO MOVE SAFE
"""

{:ok, script} =
  if floor == "sim",
    do: Script.parse_file("priv/sims/machining_cycle.vws"),
    else: Script.parse(obedient_cycle)

machine = Bench.machine()

# VWS_STATUS runs at high priority: on a node with more polling than it can do, nothing at
# normal priority would run any more — this script included.
Process.flag(:priority, :high)

gc_memory = fn ->
  for p <- Process.list(), do: :erlang.garbage_collect(p)
  :erlang.memory(:total)
end

cec_memory = &Bench.cec_memory/1

ids = fn n -> for i <- 1..n, do: "S#{n}-#{String.pad_leading(Integer.to_string(i), 4, "0")}" end

{:ok, sims_sup} = DynamicSupervisor.start_link(strategy: :one_for_one)

# The simulated floor of one workstation, every device on a loopback endpoint; returns the
# workstation's links and partitions.
start_floor = fn ws ->
  {:ok, _} =
    DynamicSupervisor.start_child(
      sims_sup,
      {Vws.Sim.Floor,
       workstation: ws,
       time_scale: scale,
       daq1: "loopback:daq1-#{ws}",
       daq2: "loopback:daq2-#{ws}",
       hydraulic: {Vws.Peers.HydraulicController, [listen: "loopback:hyd-#{ws}"]},
       ge2000: [endpoint: "loopback:ge-#{ws}"],
       robot: [endpoint: "loopback:val-#{ws}"],
       mhs: true}
    )

  :ok = Vws.Peers.HydraulicController.await_ready(Vws.Sim.Floor.hydraulic_controller(ws), 30_000)
  :ok = Vws.Sim.Plant.set_part(Vws.Sim.Floor.plant(ws), :tray1, true)
  {links, partitions} = Vws.CEC.Workstation.device_links(ws, Vws.Sim.Floor.devices(ws), [])
  %{links: links, partitions: partitions}
end

obedient =
  for p <- [:robot, :monarch, :gripper, :fixture, :vacuum, :hydraulic],
      do: {p, [module: Bench.Obedient, interlocks: :off, link: :none, options: [ms: command_ms]]}

wait_until = &Bench.wait_until/2

ready? = fn ws ->
  Vws.CEC.SunComm.listening(ws) != nil and
    (floor != "sim" or
       (not String.starts_with?(Vws.CEC.SunComm.Status.answer(ws, "GRIPPER"), "NO DATA") and
          Vws.CEC.SunComm.Status.answer(ws, "MONARCH") == "IDLE"))
end

step = fn n ->
  ws_ids = ids.(n)
  # what the previous step left behind is gone before the first sample
  Process.sleep(1_000)
  m0 = gc_memory.()

  wiring =
    if floor == "sim",
      do: Map.new(ws_ids, &{&1, start_floor.(&1)}),
      else: Map.new(ws_ids, &{&1, %{links: [], partitions: obedient}})

  t0 = System.monotonic_time(:millisecond)

  for ws <- ws_ids do
    {:ok, _} =
      Vws.CEC.Workstation.start(
        id: ws,
        wc: "loopback:wc-#{ws}",
        links: wiring[ws].links,
        partitions: wiring[ws].partitions
      )
  end

  ready = wait_until.(fn -> Enum.all?(ws_ids, ready?) end, 60_000 + n * 100)
  started_s = (System.monotonic_time(:millisecond) - t0) / 1000

  clients =
    for ws <- ws_ids do
      {:ok, client} = Client.connect("loopback:wc-#{ws}")
      {ws, client}
    end

  _ = gc_memory.()
  cec = Enum.map(ws_ids, cec_memory)
  processes = length(Process.list())

  stats_before = if floor == "sim", do: Map.new(ws_ids, &{&1, VwsStatus.stats(&1)}), else: %{}

  deadline = System.monotonic_time(:millisecond) + seconds * 1_000
  {cpu0, _} = :erlang.statistics(:runtime)
  util0 = :scheduler.sample()

  tasks =
    for {ws, client} <- clients do
      Task.async(fn ->
        Stream.unfold(:go, fn
          :halt ->
            nil

          :go ->
            if System.monotonic_time(:millisecond) >= deadline do
              nil
            else
              s = Runner.run(client, script)
              {{ws, s}, if(s.result == :completed, do: :go, else: :halt)}
            end
        end)
        |> Enum.to_list()
      end)
    end

  cec_during =
    Task.async(fn ->
      Process.sleep(div(seconds * 1_000, 2))
      Enum.map(ws_ids, cec_memory)
    end)

  sampler =
    Task.async(fn ->
      Stream.repeatedly(fn ->
        Process.sleep(500)
        :erlang.memory(:total)
      end)
      |> Enum.take_while(fn _ -> System.monotonic_time(:millisecond) < deadline end)
      |> Enum.max(fn -> 0 end)
    end)

  runs = tasks |> Task.await_many(seconds * 1_000 + 600_000) |> List.flatten()
  peak = Task.await(sampler, 60_000)
  cec_during = Task.await(cec_during, 600_000)
  {cpu1, _} = :erlang.statistics(:runtime)
  util = Bench.normal_utilization(util0)
  wall_s = seconds + max(System.monotonic_time(:millisecond) - deadline, 0) / 1000

  polls =
    if floor == "sim" do
      for ws <- ws_ids, reduce: %{polls: 0, missed: 0, late: 0} do
        acc ->
          after_ = VwsStatus.stats(ws)
          before = stats_before[ws]

          %{
            polls: acc.polls + after_.polls - before.polls,
            missed: acc.missed + after_.missed - before.missed,
            late: acc.late + after_.late - before.late
          }
      end
    end

  for {_ws, client} <- clients, do: Client.close(client)
  # the polls stop first, so the rest of the node gets the CPU back to stop the workstations
  for ws <- ws_ids, pid = Vws.CEC.Partition.whereis(ws, :vws_status), do: :sys.suspend(pid)
  for ws <- ws_ids, do: Vws.CEC.Workstation.stop(ws)

  for {_, pid, _, _} <- DynamicSupervisor.which_children(sims_sup),
      do: DynamicSupervisor.terminate_child(sims_sup, pid)

  completed = Enum.filter(runs, fn {_ws, s} -> s.result == :completed end)
  stopped = Enum.reject(runs, fn {_ws, s} -> s.result == :completed end)
  idle = Enum.filter(clients, fn {ws, _} -> not Enum.any?(runs, &(elem(&1, 0) == ws)) end)

  %{
    n: n,
    ready: ready,
    started_s: started_s,
    cec: Enum.sum(cec) / n,
    cec_max: Enum.max(cec ++ cec_during),
    peak: (peak - m0) / n,
    processes: processes,
    cycles: length(runs),
    completed: length(completed),
    stopped: stopped,
    idle: length(idle),
    cycle_ms: Enum.map(completed, fn {_ws, s} -> s.elapsed_ms end),
    cpu: (cpu1 - cpu0) / 1000 / wall_s,
    util: util,
    polls: polls,
    ok?: ready == :ok and stopped == [] and idle == [] and completed != []
  }
end

results =
  Enum.reduce_while(counts, [], fn n, acc ->
    r = step.(n)

    IO.puts(
      :stderr,
      "  … #{n} workstations: #{if r.ok?, do: "every cycle completed", else: "FAILED"}"
    )

    if r.ok? or Keyword.get(opts, :all, false), do: {:cont, acc ++ [r]}, else: {:halt, acc ++ [r]}
  end)

sustained = results |> Enum.filter(& &1.ok?) |> Enum.map(& &1.n) |> Enum.max(fn -> 0 end)
# (a stage that allocates nothing shows as 0.00, not as a small negative of the noise)
mb = fn bytes -> :erlang.float_to_binary(max(bytes, 0) / 1_048_576, decimals: 2) end

rows =
  for r <- results do
    cycle =
      case r.cycle_ms do
        [] -> "-"
        ms -> "#{Bench.pct(ms, 0.5)}/#{Bench.pct(ms, 0.99)}"
      end

    polls =
      case r.polls do
        nil ->
          ""

        p ->
          due = p.polls + p.missed

          "  VWS_STATUS #{Bench.thousands(p.polls / seconds)} polls/s, missed #{Float.round(p.missed * 100 / max(due, 1), 1)} %, late #{Float.round(p.late * 100 / max(p.polls, 1), 1)} %"
      end

    failures =
      r.stopped
      |> Enum.map(fn {_ws, s} -> "#{s.stopped.source}: #{s.stopped.reason}" end)
      |> Enum.frequencies()
      |> Enum.sort_by(&(-elem(&1, 1)))
      |> Enum.take(2)
      |> Enum.map(fn {why, k} -> "\n        #{k}× #{String.slice(why, 0, 110)}" end)

    "  #{String.pad_leading(Integer.to_string(r.n), 5)}  " <>
      "#{String.pad_leading(mb.(r.cec), 8)} #{String.pad_leading(mb.(r.cec_max), 8)} #{String.pad_leading(mb.(r.peak), 8)}  " <>
      "#{String.pad_leading("#{r.completed}/#{r.cycles}", 11)}  #{String.pad_leading(cycle, 16)}  " <>
      "#{String.pad_leading(:erlang.float_to_binary(r.cpu, decimals: 2), 5)}  #{String.pad_leading("#{round(r.util * 100)} %", 5)}  " <>
      "#{if r.ok?, do: "yes", else: "NO"}#{if r.ready != :ok, do: " (not all ready in time)", else: ""}#{if r.idle > 0, do: " (#{r.idle} WCs never finished a cycle)", else: ""}\n" <>
      "         started in #{Float.round(r.started_s, 1)} s, #{Bench.thousands(r.processes)} processes#{polls}" <>
      Enum.join(failures)
  end

cec_1000 = Enum.find(results, &(&1.n == 1000))

floor_text =
  if floor == "sim",
    do:
      "each with its whole simulated floor (plant, DAQ #1, DAQ #2 + hydraulic controller on HPIB, GE-2000 on DNC, VAL II on DDCMP, MHS), time ×#{scale}",
    else:
      "obedient partitions (every command DONE after #{command_ms} ms), no devices, no DAQ polling"

IO.puts(
  Enum.join(
    ["Scale: workstations on one node, all on loopback endpoints" | machine] ++
      [
        "  floor          #{floor_text}",
        "  script         #{length(script.steps)} steps, run again and again by each workstation's own WC for #{seconds} s (polling every 100 ms)",
        "      N    CEC MB  CEC max   all MB  cycles done  cycle ms p50/p99  cores  sched  all completed"
      ] ++
      rows ++
      [
        "  sustained      #{sustained} workstations with every cycle completing (largest count tried: #{List.last(results).n})",
        "  target         1,000 workstations, < 2 MB of CEC memory each, every cycle completing: " <>
          cond do
            cec_1000 && cec_1000.ok? && cec_1000.cec_max < 2 * 1_048_576 ->
              "MET"

            cec_1000 ->
              "MISSED (#{if cec_1000.ok?, do: "cycles completed", else: "cycles did not all complete"}; CEC at most #{mb.(cec_1000.cec_max)} MB)"

            true ->
              "MISSED: sustained #{sustained} of 1,000 (#{Float.round(sustained / 10, 1)} %)"
          end
      ],
    "\n"
  )
)
