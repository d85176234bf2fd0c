# What one workstation costs the CEC itself, with its equipment in other OS processes (issue 29).
#
#     ELIXIR_ERL_OPTIONS="+sbwt none +sbwtdcpu none +sbwtdio none" \
#       nice -n 15 mix run bench/cec_cost.exs [--counts 1,100,500,1000] [--seconds 10]
#       [--poll-ms 20] [--wc-ms 100] [--floors 2] [--daq canned|sim] [--pin]
#       [--cycles 1,20] [--cycle-seconds 30]
#
# This node is the CEC: it runs only the N workstations (`Vws.CEC.Workstation`). Their equipment
# runs in --floors other OS processes (`:peer` nodes over stdio, no distribution), reached over
# TCP on 127.0.0.1 as a real cell's would be over its LAN and terminal servers; the WCs run
# there too. With --pin the CEC's OS process is pinned to CPU 0 and the floor nodes to CPU 1
# (`taskset`), so the CEC has one core of its own — of a machine that other work shares: the
# load average is printed at the start and the end of every step.
#
# For each N, windows of --seconds:
#
#   F. the floor (--daq canned): before the workstations start, one bare process per workstation
#      on this node sends its DAQ #1 the very bytes of a poll every --poll-ms over an active-N
#      socket and reads the answer lines, nothing else. CPU per exchange = the least a poll
#      over TCP can cost this node; each poll's CPU is printed as a multiple of it.
#   A. polls: every workstation's VWS_STATUS polls its DAQ #1 every --poll-ms. DAQ #1 is, with
#      --daq canned (default), a bench-only SCPI responder that answers every poll with fixed
#      readings (the cheapest equipment there can be: what it costs the floor nodes does not
#      hold the CEC up); with --daq sim, `Vws.Sim.Floor`'s DAQ #1 and its plant.
#      CPU per poll = the CEC's CPU in the window / the polls made in it.
#   B. polls + WC: besides, each workstation's WC sends a status string (`S0001 ROBOT_CMD`, a new
#      sequence number each time) every --wc-ms and reads the reply.
#      CPU per WC exchange = (CPU in B - CPU rate of A × B's length) / exchanges.
#   Threads: in A, the time of the BEAM's threads by what they did (`:msacc`: emulator — Erlang
#   code —, gc, port — the drivers' I/O —, check_io, other, aux), per poll, sleep left out.
#   Own work: the reductions of the workstations' VWS_STATUS and HPIB processes per poll in A,
#   and of SUN_COMM per WC string in B — what those processes did themselves, counted apart
#   (no subtraction, so neither the machine's load nor the polls in B change it).
#   The CEC's CPU is its OS process's user + system time (/proc/self/stat), and the schedulers'
#   busy time (`:scheduler.sample/0`; it leaves out the schedulers' spinning when idle: run with
#   the ELIXIR_ERL_OPTIONS above so the OS figure leaves it out too).
#   VWS_STATUS period error: |time between two polls of a workstation - the period in force|
#   (k · poll period, k the nearest whole number ≥ 1: shedding stretches the period), from the
#   `[:vws, :vws_status, :poll]` event of up to 50 workstations (a handler on so few costs the
#   CEC little); p50/p99 of those, and the counts of missed and failed polls of all of them.
#   Memory per workstation: the workstation's processes and ETS tables (as bench/scale.exs).
#   Fairness: each workstation's polls per second in the window (lowest, median, highest), the
#   periods in force (`VwsStatus.stats/1`'s period_ms) and how many workstations read NO DATA
#   at the end. --no-shedding turns VWS_STATUS's load shedding off, to compare.
#
# With --cycles N1,…: for each, N workstations with their whole simulated floors
# (`Vws.Sim.Floor` at ×20: plant, both DAQs, the hydraulic controller, the GE-2000 on DNC, the
# VAL II on DDCMP, the MHS) in the floor nodes, each WC running `priv/sims/machining_cycle.vws`
# again and again for --cycle-seconds. It counts what crossed the CEC's links (telemetry: DDCMP
# frames, DNC blocks, WC strings, polls) and shares the CEC's CPU out by the reductions of the
# workstations' processes by role (the DDCMP link and VAL connection, the DNC link, the HPIB
# devices, VWS_STATUS, SUN_COMM, the rest): the CPU per DDCMP frame, per DNC block, per poll and
# per WC string, on the assumption that a reduction costs the same wherever it is spent (the
# kernel's work for each socket is shared out the same way).

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench
alias Vws.Partitions.VwsStatus

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [
      counts: :string,
      seconds: :integer,
      poll_ms: :integer,
      wc_ms: :integer,
      floors: :integer,
      daq: :string,
      pin: :boolean,
      cycles: :string,
      cycle_seconds: :integer,
      shedding: :boolean
    ]
  )

ints = fn text -> text |> String.split(",", trim: true) |> Enum.map(&String.to_integer/1) end
counts = ints.(Keyword.get(opts, :counts, "1,100,500,1000"))
seconds = Keyword.get(opts, :seconds, 10)
poll_ms = Keyword.get(opts, :poll_ms, 20)
wc_ms = Keyword.get(opts, :wc_ms, 100)
n_floors = Keyword.get(opts, :floors, 2)
daq_kind = Keyword.get(opts, :daq, "canned")
pin = Keyword.get(opts, :pin, false)
cycle_counts = ints.(Keyword.get(opts, :cycles, ""))
cycle_seconds = Keyword.get(opts, :cycle_seconds, 30)

# --no-shedding: every VWS_STATUS polls at its period or misses (Vws.Partitions.VwsStatus.Shedding)
shedding = if Keyword.get(opts, :shedding, true), do: [], else: [shedding: false]

# The floor nodes' code: compiled here, loaded there (a module of a script has no .beam file).
floor_host = ~S"""
defmodule Bench.FloorHost do
  @moduledoc false
  # Runs in a floor node: the equipment of many workstations, and their WCs.

  def setup do
    {:ok, _} = Application.ensure_all_started(:logger)
    Logger.configure(level: :error)
    {:ok, _} = Application.ensure_all_started(:vws)
    :ok
  end

  ## DAQ #1 alone

  # One listener for every workstation of this node; each connection its own process.
  def canned_daq do
    parent = self()

    pid =
      spawn(fn ->
        {:ok, l} = :gen_tcp.listen(0, [:binary, packet: :line, active: false, reuseaddr: true, backlog: 1024])
        {:ok, port} = :inet.port(l)
        send(parent, {:port, port})
        accept(l)
      end)

    receive do
      {:port, port} -> {pid, "tcp://127.0.0.1:#{port}"}
    end
  end

  defp accept(l) do
    {:ok, s} = :gen_tcp.accept(l)
    pid = spawn(fn -> receive(do: (:go -> serve(s, %{}))) end)
    :ok = :gen_tcp.controlling_process(s, pid)
    send(pid, :go)
    accept(l)
  end

  defp serve(s, relays) do
    :ok = :inet.setopts(s, active: :once, nodelay: true)

    receive do
      {:tcp, ^s, line} ->
        {reply, relays} = answer(Vws.Codecs.SCPI.decode_command(line), relays)
        if reply, do: :gen_tcp.send(s, reply)
        serve(s, relays)

      {:tcp_closed, ^s} ->
        :ok
    end
  end

  # answers cached per line: the equipment's own work is not what is measured
  defp answer({:ok, {:meas_volt_dc?, chans}}, relays),
    do: {cached({:v, length(chans)}, fn -> List.duplicate(0.0, length(chans)) end), relays}

  defp answer({:ok, {:meas_res?, chans}}, relays),
    do: {cached({:r, length(chans)}, fn -> List.duplicate(120.0, length(chans)) end), relays}

  defp answer({:ok, {:rout_clos?, chans}}, relays),
    do: {Vws.Codecs.SCPI.encode_response(Enum.map(chans, &Map.get(relays, &1, false))), relays}

  defp answer({:ok, {:rout_clos, chans}}, relays),
    do: {nil, Enum.reduce(chans, relays, &Map.put(&2, &1, true))}

  defp answer({:ok, {:rout_open, chans}}, relays),
    do: {nil, Enum.reduce(chans, relays, &Map.put(&2, &1, false))}

  defp answer({:ok, :syst_err?}, relays), do: {"+0,\"No error\"\n", relays}
  defp answer(_other, relays), do: {nil, relays}

  defp cached(key, values) do
    case Process.get(key) do
      nil ->
        bin = IO.iodata_to_binary(Vws.Codecs.SCPI.encode_response(values.()))
        Process.put(key, bin)
        bin

      bin ->
        bin
    end
  end

  def sim_daqs(ids) do
    for ws <- ids do
      {:ok, _} =
        DynamicSupervisor.start_child(
          Vws.EquipmentSupervisor,
          {Vws.Sim.Floor, workstation: ws, time_scale: 20.0, daq2: false}
        )

      {ws, Vws.Sim.Floor.daq1_endpoint(ws)}
    end
  end

  ## Whole floors

  def floors(ids) do
    for ws <- ids do
      {:ok, _} =
        DynamicSupervisor.start_child(
          Vws.EquipmentSupervisor,
          {Vws.Sim.Floor,
           workstation: ws,
           time_scale: 20.0,
           hydraulic: {Vws.Peers.HydraulicController, []},
           ge2000: true,
           robot: true,
           mhs: true}
        )

      :ok = Vws.Peers.HydraulicController.await_ready(Vws.Sim.Floor.hydraulic_controller(ws), 30_000)
      :ok = Vws.Sim.Plant.set_part(Vws.Sim.Floor.plant(ws), :tray1, true)
      {ws, Vws.Sim.Floor.devices(ws)}
    end
  end

  def stop_all do
    for {_, pid, _, _} <- DynamicSupervisor.which_children(Vws.EquipmentSupervisor),
        do: DynamicSupervisor.terminate_child(Vws.EquipmentSupervisor, pid)

    :ok
  end

  ## WCs

  # Each WC sends a status string every `period` ms (random phase) for `ms` and puts its round
  # trips (µs) in :bench_wc. (Each VM has its own monotonic clock: durations cross, not times.)
  def status_wcs(targets, period, ms) do
    stop = System.monotonic_time(:millisecond) + ms

    for {ws, endpoint} <- targets do
      spawn(fn ->
        "tcp://127.0.0.1:" <> port = endpoint
        {:ok, s} = :gen_tcp.connect(~c"127.0.0.1", String.to_integer(port), [:binary, active: false, nodelay: true])
        start = System.monotonic_time(:millisecond) + :rand.uniform(period)
        times = status_loop(s, 1, start, period, stop, [])
        :gen_tcp.close(s)
        :ets.insert(:bench_wc, {:status, ws, times})
      end)
    end

    :ok
  end

  def wc_table do
    spawn(fn ->
      :ets.new(:bench_wc, [:public, :named_table, :duplicate_bag])
      Process.sleep(:infinity)
    end)

    Process.sleep(50)
    :ok
  end

  # what the WCs of one kind (:status, :cycles) put in, taken out: a WC still finishing a phase
  # that is over does not count in the next
  def wc_results(kind) do
    rows = :ets.match_object(:bench_wc, {kind, :_, :_})
    :ets.match_delete(:bench_wc, {kind, :_, :_})
    for {_kind, ws, list} <- rows, do: {ws, list}
  end

  defp status_loop(s, seq, at, period, stop, acc) do
    now = System.monotonic_time(:millisecond)

    cond do
      at >= stop ->
        acc

      at > now ->
        Process.sleep(at - now)
        status_loop(s, seq, at, period, stop, acc)

      true ->
        line =
          %Vws.Codecs.WC.CommandString{
            sequence: seq,
            commands: [%Vws.Codecs.WC.Command{letter: "S", set: :status, number: 1, text: "ROBOT_CMD"}]
          }
          |> Vws.Codecs.WC.CommandString.encode()
          |> IO.iodata_to_binary()

        t0 = System.monotonic_time(:microsecond)

        if :gen_tcp.send(s, line) == :ok and recv_reply(s, "") do
          dt = System.monotonic_time(:microsecond) - t0
          status_loop(s, rem(seq, 9_999) + 1, at + period, period, stop, [dt | acc])
        else
          # the connection is gone: this WC stops here
          [:lost | acc]
        end
    end
  end

  defp recv_reply(s, got) do
    case :gen_tcp.recv(s, 0, 5_000) do
      {:ok, more} ->
        got = got <> more
        if String.ends_with?(got, "\r\n"), do: true, else: recv_reply(s, got)

      {:error, _} ->
        false
    end
  end

  # The machining cycle again and again until `stop`; the results in :bench_wc.
  def cycle_wcs(targets, script_path, ms) do
    stop = System.monotonic_time(:millisecond) + ms
    {:ok, script} = Vws.Peers.WC.Script.parse_file(script_path)

    for {ws, endpoint} <- targets do
      spawn(fn ->
        {:ok, client} = Vws.Peers.WC.Client.connect(endpoint)
        runs = cycle_loop(client, script, stop, [])
        Vws.Peers.WC.Client.close(client)
        :ets.insert(:bench_wc, {:cycles, ws, runs})
      end)
    end

    :ok
  end

  defp cycle_loop(client, script, stop, acc) do
    if System.monotonic_time(:millisecond) >= stop do
      acc
    else
      s = Vws.Peers.WC.Runner.run(client, script)
      r = if s.result == :completed, do: :completed, else: {:stopped, s.stopped.source, s.stopped.reason}
      if r == :completed, do: cycle_loop(client, script, stop, [r | acc]), else: [r | acc]
    end
  end
end
"""

[{host_mod, host_bin}] = Code.compile_string(floor_host)

erl = System.find_executable("erl") |> String.to_charlist()
pa = Enum.flat_map(:code.get_path(), &[~c"-pa", &1])

floors =
  for i <- 1..n_floors do
    exec = if pin, do: {~c"/usr/bin/taskset", [~c"-c", ~c"1", erl]}, else: erl
    {:ok, peer, _node} = :peer.start_link(%{connection: :standard_io, exec: exec, args: pa})

    {:module, _} =
      :peer.call(peer, :code, :load_binary, [host_mod, ~c"bench_floor_host", host_bin])

    :ok = :peer.call(peer, host_mod, :setup, [], 60_000)
    :ok = :peer.call(peer, host_mod, :wc_table, [])
    {i, peer}
  end

if pin do
  {_, 0} = System.cmd("taskset", ["-a", "-pc", "0", System.pid()])
end

machine = Bench.machine()
Process.flag(:priority, :high)

loadavg = fn ->
  File.read!("/proc/loadavg") |> String.split() |> Enum.take(3) |> Enum.join(" ")
end

floor_pids = for {_, peer} <- floors, do: :peer.call(peer, :os, :getpid, [])

# an OS process's CPU time, µs, {user, system} (every thread): the CEC's ("self"), or the floor
# nodes'
os_times_of = fn pid ->
  [_pid, rest] = String.split(File.read!("/proc/#{pid}/stat"), ") ", parts: 2)
  fields = String.split(rest)
  us = fn i -> div(String.to_integer(Enum.at(fields, i)) * 1_000_000, 100) end
  {us.(11), us.(12)}
end

os_cpu_of = fn pid ->
  {user, system} = os_times_of.(pid)
  user + system
end

floor_cpu = fn -> Enum.sum(Enum.map(floor_pids, os_cpu_of)) end

# the CEC's OS CPU time, µs (user + system, every thread)
os_cpu = fn -> os_cpu_of.("self") end

# a window: its OS CPU µs, the schedulers' busy µs, wall µs
window = fn fun ->
  c0 = os_cpu.()
  {_, sys0} = os_times_of.("self")
  f0 = floor_cpu.()
  u0 = :scheduler.sample()
  {r0, _} = :erlang.statistics(:exact_reductions)
  t0 = System.monotonic_time(:microsecond)
  result = fun.()
  wall = System.monotonic_time(:microsecond) - t0
  {r1, _} = :erlang.statistics(:exact_reductions)
  busy = Bench.normal_utilization(u0) * System.schedulers_online() * wall
  floor = floor_cpu.() - f0
  {_, sys1} = os_times_of.("self")

  %{
    cpu: os_cpu.() - c0,
    sys: sys1 - sys0,
    busy: busy,
    wall: wall,
    reds: r1 - r0,
    floor: floor,
    result: result
  }
end

split = fn ids ->
  Enum.group_by(Enum.with_index(ids), fn {_, i} -> rem(i, n_floors) + 1 end, &elem(&1, 0))
end

on_floors = fn ids, fun ->
  Enum.flat_map(split.(ids), fn {f, part} -> fun.(:proplists.get_value(f, floors), part) end)
end

ready? = fn ws ->
  Vws.CEC.SunComm.listening(ws) != nil and
    not String.starts_with?(Vws.CEC.SunComm.Status.answer(ws, "GRIPPER"), "NO DATA")
end

wait_until = &Bench.wait_until/2

wc_endpoint = fn ws -> Vws.Links.Endpoint.to_string(Vws.CEC.SunComm.listening(ws)) end

poll_stats = fn ids ->
  stats = Map.new(ids, &{&1, VwsStatus.stats(&1)})

  %{
    polls: Enum.sum(for {_, st} <- stats, do: st.polls),
    missed: Enum.sum(for {_, st} <- stats, do: st.missed),
    failed: Enum.sum(for {_, st} <- stats, do: st.failed),
    per: Map.new(stats, fn {ws, st} -> {ws, st.polls} end),
    periods: Enum.frequencies(for {_, st} <- stats, do: Map.get(st, :period_ms, poll_ms)),
    no_data:
      Enum.count(
        ids,
        &String.starts_with?(Vws.CEC.SunComm.Status.answer(&1, "GRIPPER"), "NO DATA")
      )
  }
end

diff = fn a, b ->
  %{
    polls: b.polls - a.polls,
    missed: b.missed - a.missed,
    failed: b.failed - a.failed,
    per: Enum.map(b.per, fn {ws, n} -> n - a.per[ws] end),
    periods: b.periods,
    no_data: b.no_data
  }
end

# poll start times of the sampled workstations
samples = :ets.new(:samples, [:public, :duplicate_bag, write_concurrency: true])

sample_polls = fn sampled ->
  :ok =
    Vws.Telemetry.attach(
      :bench_cec_cost,
      [:vws, :vws_status, :poll],
      fn _event, m, md, {table, set} ->
        if MapSet.member?(set, md.workstation),
          do: :ets.insert(table, {md.workstation, md.seq, m.started_at})
      end,
      {samples, MapSet.new(sampled)}
    )
end

period_errors = fn ->
  :ets.tab2list(samples)
  |> Enum.group_by(&elem(&1, 0), &{elem(&1, 1), elem(&1, 2)})
  |> Enum.flat_map(fn {_ws, polls} ->
    polls
    |> Enum.sort()
    |> Enum.chunk_every(2, 1, :discard)
    # against the period in force: shedding polls every k periods (k = the nearest multiple);
    # a slot missed altogether is counted as missed, not here
    |> Enum.map(fn [{_, a}, {_, b}] ->
      p = poll_ms * 1_000
      k = max(round((b - a) / p), 1)
      abs(b - a - k * p)
    end)
  end)
end

stop_workstations = fn ids ->
  for ws <- ids, pid = Vws.CEC.Partition.whereis(ws, :vws_status), do: :sys.suspend(pid)
  for ws <- ids, do: Vws.CEC.Workstation.stop(ws)
  for {_, peer} <- floors, do: :ok = :peer.call(peer, host_mod, :stop_all, [], 600_000)
end

# By role: what the workstations' own processes did in a window (the polls' VWS_STATUS and
# HPIB, the WC's SUN_COMM), and, with the whole floors, the CPU per DDCMP/DNC message, per poll
# and per WC string.
# The reductions of the workstations' processes by role (their initial call), to share the
# node's CPU out: a process's reductions are the BEAM's count of the work it did.
roles = %{
  Vws.Links.DDCMP.Link => "DDCMP",
  Vws.Links.VAL.Connection => "DDCMP",
  Vws.Links.DNC.Link => "DNC",
  Vws.Links.HPIB.Device => "HPIB",
  Vws.Partitions.VwsStatus => "VWS_STATUS",
  Vws.CEC.SunComm.Server => "SUN_COMM"
}

reds_by_role = fn ids ->
  walk = fn walk, sup ->
    Enum.flat_map(Supervisor.which_children(sup), fn
      {_, pid, :supervisor, _} when is_pid(pid) -> [pid | walk.(walk, pid)]
      {_, pid, _, _} when is_pid(pid) -> [pid]
      _ -> []
    end)
  end

  for ws <- ids,
      sup = Vws.CEC.Workstation.whereis(ws),
      pid <- walk.(walk, sup),
      {:reductions, r} <- [Process.info(pid, :reductions)],
      reduce: %{} do
    acc ->
      role =
        case :proc_lib.translate_initial_call(pid) do
          {m, _, _} -> Map.get(roles, m, "the rest")
          _ -> "the rest"
        end

      Map.update(acc, {role, pid}, r, &(&1 + r))
  end
end

# each process's reductions between two reds_by_role/1 (one started between them: all of its
# own), summed by role
role_delta = fn reds0, reds1 ->
  Enum.reduce(reds1, %{}, fn {{role, pid}, r}, acc ->
    Map.update(
      acc,
      role,
      r - Map.get(reds0, {role, pid}, 0),
      &(&1 + r - Map.get(reds0, {role, pid}, 0))
    )
  end)
end

# The floor: what the poll's TCP exchange alone costs this node. One bare process per
# workstation, on this node, sends DAQ #1 the very bytes of a VWS_STATUS poll at the same rate
# (absolute timers, the same phases spread) over an active-N socket, as the HPIB device's is,
# and reads the answer lines — nothing else: no decoding, no mailbox, no event. Its CPU per
# exchange is the least any poll over TCP could cost here; a poll's cost is set beside it.
poll_commands = Vws.Links.DAQ.poll_commands(Vws.Links.DAQ.new())
poll_bytes = poll_commands |> Enum.map(&Vws.Codecs.SCPI.encode_command/1) |> IO.iodata_to_binary()
# (every poll command is a query: one answer line each)
poll_lines = length(poll_commands)

bare_poller = fn endpoint, first_at, counter ->
  "tcp://127.0.0.1:" <> port = endpoint

  {:ok, socket} =
    :gen_tcp.connect(~c"127.0.0.1", String.to_integer(port), [:binary, active: 8, nodelay: true])

  answer = fn answer, lines ->
    receive do
      {:tcp, ^socket, bytes} ->
        lines = lines - length(:binary.matches(bytes, "\n"))
        if lines > 0, do: answer.(answer, lines), else: :ok

      {:tcp_passive, ^socket} ->
        :ok = :inet.setopts(socket, active: 8)
        answer.(answer, lines)
    end
  end

  poll = fn poll, at ->
    :erlang.start_timer(at, self(), :poll, abs: true)

    receive do
      {:timeout, _, :poll} ->
        :ok = :gen_tcp.send(socket, poll_bytes)
        :ok = answer.(answer, poll_lines)
        :counters.add(counter, 1, 1)
        poll.(poll, at + poll_ms)

      :stop ->
        :gen_tcp.close(socket)
    end
  end

  poll.(poll, first_at)
end

# the BEAM's threads' time by what they did (microstate accounting) over --seconds, sleep left out
msacc_window = fn ->
  :msacc.start(seconds * 1_000)

  for %{counters: c} <- :msacc.stats(), {state, us} <- c, state != :sleep, reduce: %{} do
    acc -> Map.update(acc, state, us, &(&1 + us))
  end
end

# window F: the bare pollers of `daqs` ({ws, endpoint}) for --seconds, after a second's warm-up
floor_window = fn daqs ->
  counter = :counters.new(1, [])
  start = System.monotonic_time(:millisecond) + 200

  pids =
    for {{_ws, endpoint}, i} <- Enum.with_index(daqs) do
      first_at = start + rem(i * 7_919, poll_ms)
      spawn(fn -> bare_poller.(endpoint, first_at, counter) end)
    end

  Process.sleep(1_200)
  n0 = :counters.get(counter, 1)
  f = window.(msacc_window)
  exchanges = :counters.get(counter, 1) - n0
  for pid <- pids, do: send(pid, :stop)
  Process.sleep(200)
  Map.put(f, :exchanges, exchanges)
end

per = fn us, n -> if n > 0, do: Bench.us(us / n), else: "-" end

threads = fn states, n ->
  states
  |> Enum.filter(fn {_, us} -> us > 0 end)
  |> Enum.sort_by(&(-elem(&1, 1)))
  |> Enum.map_join(", ", fn {state, us} -> "#{state} #{per.(us, n)}" end)
end

per_n = fn x, n -> if x && n > 0, do: round(x / n), else: "-" end
line = fn label, text -> "  " <> String.pad_trailing(label, 16) <> text end

# a read of counts, and the monotonic µs of its midpoint
timed = fn fun ->
  t0 = System.monotonic_time(:microsecond)
  result = fun.()
  {result, (t0 + System.monotonic_time(:microsecond)) / 2}
end

# counts made over a span, scaled to a window of `k` times its length (failures stay counted)
scale = fn d, k ->
  %{d | polls: d.polls * k, missed: d.missed * k, per: Enum.map(d.per, &(&1 * k))}
end

scale_roles = fn reds, k -> Map.new(reds, fn {role, r} -> {role, r * k} end) end

step = fn n ->
  ids = for i <- 1..n, do: "C#{n}-#{i}"
  Process.sleep(1_000)
  load0 = loadavg.()

  daqs =
    case daq_kind do
      "canned" ->
        Enum.flat_map(split.(ids), fn {f, part} ->
          {_pid, endpoint} =
            :peer.call(:proplists.get_value(f, floors), host_mod, :canned_daq, [])

          Enum.map(part, &{&1, endpoint})
        end)

      "sim" ->
        on_floors.(ids, fn peer, part ->
          :peer.call(peer, host_mod, :sim_daqs, [part], 600_000)
        end)
    end

  f = if daq_kind == "canned", do: floor_window.(daqs)

  for {ws, endpoint} <- daqs do
    w = VwsStatus.wiring(ws, endpoint, vws_status: [poll_ms: poll_ms] ++ shedding)

    {:ok, _} =
      Vws.CEC.Workstation.start(
        id: ws,
        wc: "tcp://127.0.0.1:0",
        links: w.links,
        partitions: w.partitions
      )
  end

  ready = wait_until.(fn -> Enum.all?(ids, ready?) end, 60_000 + n * 100)
  _ = for p <- Process.list(), do: :erlang.garbage_collect(p)
  mem = Enum.map(ids, &Bench.cec_memory/1)

  sampled = Enum.take_every(ids, max(div(n, 50), 1)) |> Enum.take(50)
  :ets.delete_all_objects(samples)
  sample_polls.(sampled)

  # The counts are read around each window, and reading them takes time (a call to every
  # VWS_STATUS, a walk of every workstation's processes): seconds for 1,000 on a saturated node,
  # while the polls go on. Each read is timed (its midpoint), and the counts between two reads
  # are scaled to the window's length: polls in window = counted × window / span.
  {roles0, rm0} = timed.(fn -> reds_by_role.(ids) end)
  {s0, m0} = timed.(fn -> poll_stats.(ids) end)
  # the BEAM's threads' time by what they did (microstate accounting), for window A
  a = window.(msacc_window)

  {s1, m1} = timed.(fn -> poll_stats.(ids) end)
  {roles1, rm1} = timed.(fn -> reds_by_role.(ids) end)
  errors_a = period_errors.()
  :ets.delete_all_objects(samples)

  targets = Enum.map(ids, &{&1, wc_endpoint.(&1)})
  stop = System.monotonic_time(:millisecond) + seconds * 1_000

  b =
    window.(fn ->
      on_floors.(Enum.map(targets, &elem(&1, 0)), fn peer, part ->
        part = MapSet.new(part)

        [
          :peer.call(peer, host_mod, :status_wcs, [
            Enum.filter(targets, &MapSet.member?(part, elem(&1, 0))),
            wc_ms,
            seconds * 1_000
          ])
        ]
      end)

      Process.sleep(max(stop - System.monotonic_time(:millisecond), 0))
    end)

  {s2, m2} = timed.(fn -> poll_stats.(ids) end)
  {roles2, rm2} = timed.(fn -> reds_by_role.(ids) end)
  errors_b = period_errors.()
  :ok = Vws.Telemetry.detach(:bench_cec_cost)
  Process.sleep(1_000)

  wc =
    Enum.flat_map(floors, fn {_, peer} ->
      :peer.call(peer, host_mod, :wc_results, [:status], 60_000)
    end)

  rtts = for {_ws, times} <- wc, t <- times, is_integer(t), do: t
  lost = for {_ws, times} <- wc, :lost <- times, do: 1
  load1 = loadavg.()
  stop_workstations.(ids)

  %{
    n: n,
    f: f,
    ready: ready,
    mem: mem,
    a: a,
    b: b,
    pa: scale.(diff.(s0, s1), a.wall / (m1 - m0)),
    pb: scale.(diff.(s1, s2), b.wall / (m2 - m1)),
    spans: {(m1 - m0) / a.wall, (m2 - m1) / b.wall},
    errors_a: errors_a,
    errors_b: errors_b,
    roles_a: scale_roles.(role_delta.(roles0, roles1), a.wall / (rm1 - rm0)),
    roles_b: scale_roles.(role_delta.(roles1, roles2), b.wall / (rm2 - rm1)),
    rtts: rtts,
    lost: length(lost),
    wcs: length(wc),
    load0: load0,
    load1: load1
  }
end

IO.puts(
  Enum.join(
    [
      "CEC cost: workstations on this node, their equipment in #{n_floors} other OS processes over TCP"
      | machine
    ] ++
      [
        line.(
          "cores",
          if(pin,
            do:
              "CEC pinned to CPU 0, floor nodes to CPU 1 (both shared with the machine's other work)",
            else: "not pinned: the CEC and the floor nodes share both cores"
          )
        ),
        line.(
          "DAQ #1",
          if(daq_kind == "canned",
            do: "canned SCPI responder (fixed readings) in the floor nodes",
            else: "Vws.Sim.Floor's DAQ #1 and plant in the floor nodes"
          )
        ),
        line.(
          "rates",
          "VWS_STATUS every #{poll_ms} ms; WC status string every #{wc_ms} ms (window B); windows of #{seconds} s"
        ),
        line.(
          "scheduler",
          "#{System.schedulers_online()} schedulers; ELIXIR_ERL_OPTIONS=#{System.get_env("ELIXIR_ERL_OPTIONS") || "(none)"}"
        )
      ],
    "\n"
  )
)

# the node's own idle cost (its housekeeping, this script), taken out of every figure below
idle = window.(fn -> Process.sleep(seconds * 1_000) end)
idle_rate = idle.cpu / idle.wall
idle_busy = idle.busy / idle.wall

IO.puts(
  line.(
    "idle",
    "no workstation: #{Float.round(idle_rate * 100, 2)} % of a core (busy #{Float.round(idle_busy * 100, 2)} %), taken out of every CPU figure below"
  )
)

for n <- counts do
  r = step.(n)

  r = %{
    r
    | a: %{r.a | cpu: r.a.cpu - idle_rate * r.a.wall, busy: r.a.busy - idle_busy * r.a.wall},
      b: %{r.b | cpu: r.b.cpu - idle_rate * r.b.wall, busy: r.b.busy - idle_busy * r.b.wall}
  }

  # reductions: the BEAM's count of work done, which the machine's other load does not change
  idle_reds = idle.reds / idle.wall
  reds_poll = (r.a.reds - idle_reds * r.a.wall) / max(r.pa.polls, 1)

  reds_exchange =
    (r.b.reds - idle_reds * r.b.wall - r.pb.polls * reds_poll) / max(length(r.rtts), 1)

  cpu_a = r.a.cpu

  floor_text =
    case r.f do
      nil ->
        "- (measured with --daq canned only)"

      f ->
        f_cpu = f.cpu - idle_rate * f.wall
        ratio = cpu_a / max(r.pa.polls, 1) / max(f_cpu / max(f.exchanges, 1), 1.0e-9)

        "a bare process per workstation doing the poll's TCP exchange alone (same bytes and rate, active-N): " <>
          "#{Bench.thousands(f.exchanges / (f.wall / 1.0e6))}/s, #{per.(f_cpu, f.exchanges)} µs CPU each " <>
          "(the kernel's #{per.(f.sys, f.exchanges)} µs); a poll costs #{:erlang.float_to_binary(ratio, decimals: 2)}× that; its threads per exchange (msacc): " <>
          threads.(f.result, f.exchanges)
    end

  rate_a = r.a.cpu / r.a.wall
  busy_rate_a = r.a.busy / r.a.wall
  exchanges = length(r.rtts)
  # B's own polls charged at A's cost per poll (an overloaded node makes fewer of them)
  wc_cpu = r.b.cpu - r.pb.polls * cpu_a / max(r.pa.polls, 1)
  wc_busy = r.b.busy - r.pb.polls * r.a.busy / max(r.pa.polls, 1)
  due = fn p -> p.polls + p.missed end
  pct = fn a, b -> if b > 0, do: "#{Float.round(a * 100 / b, 1)} %", else: "-" end

  IO.puts(
    Enum.join(
      [
        "  N = #{n}#{if r.ready != :ok, do: " (not all ready in time)", else: ""}   load average #{r.load0} at the start, #{r.load1} at the end",
        line.(
          "  memory",
          "#{:erlang.float_to_binary(Enum.sum(r.mem) / n / 1_048_576, decimals: 3)} MB per workstation (max #{:erlang.float_to_binary(Enum.max(r.mem) / 1_048_576, decimals: 3)} MB)"
        ),
        line.(
          "  A polls",
          "#{Bench.thousands(r.pa.polls / (r.a.wall / 1.0e6))}/s, missed #{pct.(r.pa.missed, due.(r.pa))}, failed #{r.pa.failed}; CEC CPU #{Float.round(rate_a * 100, 1)} % of a core (busy #{Float.round(busy_rate_a * 100, 1)} %), the floor nodes #{Float.round(r.a.floor / r.a.wall * 100, 1)} %; counts read over #{Float.round(elem(r.spans, 0), 2)}× the window, scaled to it"
        ),
        line.(
          "  fairness",
          "polls per workstation per second p0 #{Float.round(Enum.min(r.pa.per) / (r.a.wall / 1.0e6), 1)}, p50 #{Float.round(Bench.pct(r.pa.per, 0.5) / (r.a.wall / 1.0e6), 1)}, max #{Float.round(Enum.max(r.pa.per) / (r.a.wall / 1.0e6), 1)}; periods in force (ms => workstations) #{inspect(r.pa.periods)}; GRIPPER NO DATA on #{r.pa.no_data} of #{n} at the end"
        ),
        line.(
          "  per poll",
          "#{per.(cpu_a, r.pa.polls)} µs CPU (busy #{per.(r.a.busy, r.pa.polls)} µs; the kernel's, system time, #{per.(r.a.sys, r.pa.polls)} µs), #{round(reds_poll)} reductions"
        ),
        line.("  floor", floor_text),
        line.(
          "  threads",
          "per poll, µs of the BEAM's threads by what they did (msacc): " <>
            threads.(r.a.result, r.pa.polls)
        ),
        line.(
          "  own work",
          "VWS_STATUS #{per_n.(r.roles_a["VWS_STATUS"], r.pa.polls)} + HPIB #{per_n.(r.roles_a["HPIB"], r.pa.polls)} reductions per poll in their own processes (window A); SUN_COMM #{per_n.(r.roles_b["SUN_COMM"], length(r.rtts))} per WC string (window B)"
        ),
        line.(
          "  period error",
          if(r.errors_a == [],
            do: "-",
            else:
              Bench.summary(r.errors_a) <>
                " µs (#{length(r.errors_a)} periods of #{min(n, 50)} workstations)"
          )
        ),
        line.(
          "  B + WC",
          "#{Bench.thousands(exchanges / (r.b.wall / 1.0e6))} exchanges/s (#{r.lost} lost), polls missed #{pct.(r.pb.missed, due.(r.pb))}, failed #{r.pb.failed}; CEC CPU #{Float.round(r.b.cpu / r.b.wall * 100, 1)} % of a core, the floor nodes #{Float.round(r.b.floor / r.b.wall * 100, 1)} %; polls per workstation per second p0 #{Float.round(Enum.min(r.pb.per) / (r.b.wall / 1.0e6), 1)}, max #{Float.round(Enum.max(r.pb.per) / (r.b.wall / 1.0e6), 1)}; periods #{inspect(r.pb.periods)}; GRIPPER NO DATA on #{r.pb.no_data}"
        ),
        line.(
          "  per exchange",
          "#{per.(wc_cpu, exchanges)} µs CPU (busy #{per.(wc_busy, exchanges)} µs), #{if exchanges > 0, do: round(reds_exchange), else: "-"} reductions (B's polls charged at A's cost); " <>
            "by reductions, #{if exchanges > 0 and r.pa.polls > 0, do: Bench.us(cpu_a / r.pa.polls * reds_exchange / max(reds_poll, 1)), else: "-"} µs (a poll's CPU × the exchange's share of its reductions: the subtraction is at the mercy of the machine's noise)"
        ),
        line.(
          "  WC round trip",
          if(r.rtts == [], do: "-", else: Bench.summary(r.rtts) <> " µs")
        ),
        line.(
          "  period error",
          if(r.errors_b == [], do: "-", else: Bench.summary(r.errors_b) <> " µs (with the WCs)")
        ),
        line.(
          "  every poll",
          if(r.pa.missed + r.pb.missed + r.pa.failed + r.pb.failed == 0 and r.lost == 0,
            do: "made and answered, every WC string answered",
            else: "NO: polls missed or failed, or WC strings lost (above)"
          )
        )
      ],
      "\n"
    )
  )
end

cycle_step = fn n ->
  ids = for i <- 1..n, do: "M#{n}-#{i}"
  Process.sleep(1_000)
  load0 = loadavg.()

  devices =
    on_floors.(ids, fn peer, part -> :peer.call(peer, host_mod, :floors, [part], 600_000) end)

  for {ws, devs} <- devices do
    {links, partitions} = Vws.CEC.Workstation.device_links(ws, devs, [])

    {:ok, _} =
      Vws.CEC.Workstation.start(
        id: ws,
        wc: "tcp://127.0.0.1:0",
        links: links,
        partitions: partitions
      )
  end

  ready =
    wait_until.(
      fn ->
        Enum.all?(ids, &(ready?.(&1) and Vws.CEC.SunComm.Status.answer(&1, "MONARCH") == "IDLE"))
      end,
      60_000 + n * 100
    )

  _ = for p <- Process.list(), do: :erlang.garbage_collect(p)
  mem = Enum.map(ids, &Bench.cec_memory/1)

  kinds = [
    ddcmp: [[:vws, :ddcmp, :frame_sent], [:vws, :ddcmp, :frame_received]],
    dnc: [[:vws, :dnc, :block_sent], [:vws, :dnc, :block_received]],
    wc: [[:vws, :sun_comm, :string_received]],
    poll: [[:vws, :vws_status, :poll]]
  ]

  counter = :counters.new(length(kinds), [:write_concurrency])

  index =
    for {{_kind, events}, i} <- Enum.with_index(kinds, 1), e <- events, into: %{}, do: {e, i}

  :ok =
    Vws.Telemetry.attach_many(
      :bench_cec_cycles,
      Map.keys(index),
      fn event, _m, _md, {c, idx} ->
        :counters.add(c, Map.fetch!(idx, event), 1)
      end,
      {counter, index}
    )

  targets = Enum.map(ids, &{&1, wc_endpoint.(&1)})
  reds0 = reds_by_role.(ids)

  w =
    window.(fn ->
      for {f, part} <- split.(ids) do
        part = MapSet.new(part)
        peer = :proplists.get_value(f, floors)

        :ok =
          :peer.call(peer, host_mod, :cycle_wcs, [
            Enum.filter(targets, &MapSet.member?(part, elem(&1, 0))),
            "priv/sims/machining_cycle.vws",
            cycle_seconds * 1_000
          ])
      end

      Process.sleep(cycle_seconds * 1_000)

      Stream.repeatedly(fn ->
        Process.sleep(500)

        Enum.flat_map(floors, fn {_, peer} ->
          :peer.call(peer, host_mod, :wc_results, [:cycles], 60_000)
        end)
      end)
      |> Enum.reduce_while([], fn got, acc ->
        acc = acc ++ got
        if length(acc) >= n, do: {:halt, acc}, else: {:cont, acc}
      end)
    end)

  :ok = Vws.Telemetry.detach(:bench_cec_cycles)
  reds1 = reds_by_role.(ids)

  by_role = role_delta.(reds0, reds1)

  counts =
    for {{kind, _}, i} <- Enum.with_index(kinds, 1),
        into: %{},
        do: {kind, :counters.get(counter, i)}

  load1 = loadavg.()
  stop_workstations.(ids)
  runs = for {_ws, rs} <- w.result, r <- rs, do: r

  %{
    n: n,
    ready: ready,
    mem: mem,
    w: w,
    counts: counts,
    runs: runs,
    load0: load0,
    load1: load1,
    by_role: by_role
  }
end

for n <- cycle_counts do
  r = cycle_step.(n)

  r = %{
    r
    | w: %{r.w | cpu: r.w.cpu - idle_rate * r.w.wall, busy: r.w.busy - idle_busy * r.w.wall}
  }

  c = r.counts
  done = Enum.count(r.runs, &(&1 == :completed))

  stopped =
    r.runs
    |> Enum.reject(&(&1 == :completed))
    |> Enum.frequencies()
    |> Enum.map(fn {{:stopped, source, reason}, k} ->
      "\n        #{k}× #{source}: #{String.slice(to_string(reason), 0, 100)}"
    end)

  IO.puts(
    Enum.join(
      [
        "  machining cycles, N = #{n}#{if r.ready != :ok, do: " (not all ready in time)", else: ""}   load average #{r.load0} at the start, #{r.load1} at the end",
        line.(
          "  memory",
          "#{:erlang.float_to_binary(Enum.sum(r.mem) / n / 1_048_576, decimals: 3)} MB per workstation (max #{:erlang.float_to_binary(Enum.max(r.mem) / 1_048_576, decimals: 3)} MB)"
        ),
        line.(
          "  cycles",
          "#{done}/#{length(r.runs)} completed in #{Float.round(r.w.wall / 1.0e6, 1)} s#{Enum.join(stopped)}"
        ),
        line.(
          "  CEC CPU",
          "#{Float.round(r.w.cpu / r.w.wall * 100, 1)} % of a core (busy #{Float.round(r.w.busy / r.w.wall * 100, 1)} %), the floor nodes #{Float.round(r.w.floor / r.w.wall * 100, 1)} %; #{if done > 0, do: Bench.thousands(r.w.cpu / done), else: "-"} µs per completed cycle"
        ),
        line.(
          "  messages",
          "#{Bench.thousands(c.poll)} polls, #{Bench.thousands(c.wc)} WC strings, #{Bench.thousands(c.ddcmp)} DDCMP frames, #{Bench.thousands(c.dnc)} DNC blocks"
        ),
        line.(
          "  by role",
          "the node's CPU shared out by the reductions of the workstations' processes (#{Bench.thousands(r.w.reds)} in all): " <>
            Enum.map_join(Enum.sort_by(r.by_role, &(-elem(&1, 1))), ", ", fn {role, reds} ->
              "#{role} #{Float.round(reds * 100 / max(r.w.reds, 1), 1)} %"
            end)
        ),
        line.(
          "  per message",
          "by that share: DDCMP #{per.(r.w.cpu * Map.get(r.by_role, "DDCMP", 0) / max(r.w.reds, 1), c.ddcmp)} µs per frame, DNC #{per.(r.w.cpu * Map.get(r.by_role, "DNC", 0) / max(r.w.reds, 1), c.dnc)} µs per block, VWS_STATUS + HPIB #{per.(r.w.cpu * (Map.get(r.by_role, "VWS_STATUS", 0) + Map.get(r.by_role, "HPIB", 0)) / max(r.w.reds, 1), c.poll)} µs per poll (the hydraulic controller's HPIB too), SUN_COMM #{per.(r.w.cpu * Map.get(r.by_role, "SUN_COMM", 0) / max(r.w.reds, 1), c.wc)} µs per WC string"
        )
      ],
      "\n"
    )
  )
end

for {_, peer} <- floors, do: :peer.stop(peer)
