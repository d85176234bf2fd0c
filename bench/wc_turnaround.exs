# WC turnaround: a status string sent to SUN_COMM, timed from the moment its last byte is
# handed to the transport until the first byte of the reply arrives — by a raw client (no
# Vws.Peers.WC.Client, no script runner), with monotonic time, right at the socket or loopback pair.
#
#     mix run bench/wc_turnaround.exs [--samples 2000] [--workstations 1000] [--poll-ms 100] [--seconds 10]
#
# 1. Alone: one workstation served on TCP, one on loopback, and a bare echo process on each
#    transport (the floor: what the machine and the transport cost); every 2 ms one status
#    string (`*nnnn*S0001ROBOT_CMD*…`, a new sequence number each time) goes to each of the four
#    in turn, 200 µs apart, the first rotating, --samples times: SUN_COMM and its floor sample by
#    sample under the same load.
# 2. --workstations on the node (loopback endpoints, no sockets), each with its own raw WC
#    polling ROBOT_CMD every --poll-ms (the WC client's polling interval), at random phases,
#    for --seconds; one of them is served on TCP instead and polled the same way, and so are two
#    bare echoes (TCP, loopback): the floor under that load.
#
# The time measured is the client's round trip: it includes the transport both ways, so it is
# an upper bound of SUN_COMM's own turnaround (last byte in → first byte out). Targets: p99 ≤
# 100 µs alone, ≤ 1 ms (one character time at 9600 Bd) with 1,000 workstations; and (issue 29)
# p99 ≤ 1.5 × the floor's p99 measured beside it, alone and with the workstations.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench
alias Vws.Links.Transport

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [samples: :integer, workstations: :integer, poll_ms: :integer, seconds: :integer]
  )

samples = Keyword.get(opts, :samples, 2_000)
n_ws = Keyword.get(opts, :workstations, 1_000)
poll_ms = Keyword.get(opts, :poll_ms, 100)
seconds = Keyword.get(opts, :seconds, 10)
machine = Bench.machine()

# a new sequence number each time, as a WC sends them (the same string again would be a
# retransmission, answered from SUN_COMM's memory of the last one)
status_of = fn seq ->
  %Vws.Codecs.WC.CommandString{
    sequence: seq,
    commands: [%Vws.Codecs.WC.Command{letter: "S", set: :status, number: 1, text: "ROBOT_CMD"}]
  }
  |> Vws.Codecs.WC.CommandString.encode()
  |> IO.iodata_to_binary()
end

statuses = List.to_tuple(for seq <- 1..9_999, do: status_of.(seq))
status = elem(statuses, 0)
# The pollers read the strings from here, not from their closure: a closure's tuple of 9,999
# strings is copied into every poller (about 1 MB each), and a thousand pollers then grew their
# heaps at the same exchange, a second of copying that stalled the whole node (p99 80–97 ms).
:persistent_term.put({:wc_turnaround, :statuses}, statuses)

defmodule Raw do
  @moduledoc false
  # A raw WC: one connection, one status string at a time, the round trip timed in native units.

  def connect(endpoint) do
    {:ok, conn} = Transport.connect(endpoint)
    if conn.module == Vws.Links.Transport.TCP, do: :ok = :inet.setopts(conn.handle, active: false)
    conn
  end

  # One exchange: µs from the send to the first byte, after reading the whole reply.
  def exchange(%{module: Vws.Links.Transport.TCP, handle: socket}, line) do
    t0 = System.monotonic_time()
    :ok = :gen_tcp.send(socket, line)
    {:ok, first} = :gen_tcp.recv(socket, 0, 5_000)
    t1 = System.monotonic_time()
    rest_tcp(socket, first)
    System.convert_time_unit(t1 - t0, :native, :nanosecond) / 1_000
  end

  def exchange(conn, line) do
    :ok = Transport.activate(conn)
    t0 = System.monotonic_time()
    :ok = Transport.send(conn, line)

    receive do
      msg ->
        t1 = System.monotonic_time()
        {:data, first} = Transport.handle_message(conn, msg)
        rest_loopback(conn, first)
        System.convert_time_unit(t1 - t0, :native, :nanosecond) / 1_000
    after
      5_000 -> :timeout
    end
  end

  defp rest_tcp(socket, got) do
    unless String.ends_with?(got, "\r\n") do
      {:ok, more} = :gen_tcp.recv(socket, 0, 5_000)
      rest_tcp(socket, got <> more)
    end
  end

  defp rest_loopback(conn, got) do
    unless String.ends_with?(got, "\r\n") do
      :ok = Transport.activate(conn)

      receive do
        msg ->
          {:data, more} = Transport.handle_message(conn, msg)
          rest_loopback(conn, got <> more)
      end
    end
  end

  # Polls every `period` ms on an absolute schedule from `start` (monotonic ms) until `stop`,
  # the lines of `lines` (a tuple) in turn.
  def poll(conn, lines, start, period, stop, acc \\ [], k \\ 0) do
    now = System.monotonic_time(:millisecond)

    cond do
      start >= stop ->
        acc

      start > now ->
        Process.sleep(start - now)
        poll(conn, lines, start, period, stop, acc, k)

      true ->
        line = elem(lines, rem(k, tuple_size(lines)))
        poll(conn, lines, start + period, period, stop, [exchange(conn, line) | acc], k + 1)
    end
  end
end

wait_listening = fn ws ->
  Stream.repeatedly(fn ->
    case Vws.CEC.SunComm.listening(ws) do
      nil -> Process.sleep(5) && nil
      endpoint -> endpoint
    end
  end)
  |> Enum.find(& &1)
end

start_ws = fn id, wc ->
  {:ok, _} = Vws.CEC.Workstation.start(id: id, wc: wc)
  wait_listening.(id)
end

# Waits `us` microseconds on the CPU (a sleep would take a millisecond at least).
pause_us = fn us ->
  until = System.monotonic_time(:microsecond) + us
  Stream.repeatedly(fn -> System.monotonic_time(:microsecond) end) |> Enum.find(&(&1 >= until))
end

# Each sample one exchange with each endpoint, in turn (which goes first rotates): SUN_COMM and
# the bare echo are measured under the same load, sample by sample.
alone = fn endpoints ->
  conns = Enum.map(endpoints, &Raw.connect/1)
  # warm up
  for k <- 1..100, conn <- conns, do: Raw.exchange(conn, elem(statuses, k))
  n = length(conns)

  samples =
    for k <- 1..samples do
      Process.sleep(2)
      order = Enum.map(0..(n - 1), &rem(&1 + k, n))
      line = elem(statuses, rem(k + 100, 9_999))
      # each exchange a moment after the one before it: what an endpoint does after its reply
      # (SUN_COMM records the dialogue then) must not fall into the next one's exchange
      Map.new(order, fn i ->
        pause_us.(200)
        {i, Raw.exchange(Enum.at(conns, i), line)}
      end)
    end

  for i <- 0..(n - 1), do: Enum.map(samples, & &1[i])
end

# The platform's floor: the same exchange against a process that echoes the bytes back over the
# same transport (active-once, as SUN_COMM reads), doing nothing else.
echo = fn endpoint ->
  parent = self()

  spawn_link(fn ->
    {:ok, listener} = Transport.listen(endpoint)
    send(parent, {:echo, Transport.listener_endpoint(listener)})
    {:ok, conn} = Transport.accept(listener, :infinity)

    Stream.repeatedly(fn ->
      :ok = Transport.activate(conn)

      receive do
        msg ->
          case Transport.handle_message(conn, msg) do
            {:data, bytes} -> Transport.send(conn, String.replace(bytes, "*", "-"))
            _ -> exit(:normal)
          end
      end
    end)
    |> Stream.run()
  end)

  receive do
    {:echo, bound} -> bound
  end
end

# --- 1. alone -----------------------------------------------------------------------------------
tcp_ep = start_ws.("ALONE-TCP", "tcp://127.0.0.1:0")
lo_ep = start_ws.("ALONE-LO", "loopback:alone")

[alone_tcp, floor_tcp, alone_lo, floor_lo] =
  alone.([tcp_ep, echo.("tcp://127.0.0.1:0"), lo_ep, echo.("loopback:echo")])

Vws.CEC.Workstation.stop("ALONE-TCP")
Vws.CEC.Workstation.stop("ALONE-LO")

# --- 2. n_ws workstations -----------------------------------------------------------------------
mem0 = :erlang.memory(:total)
t_start = System.monotonic_time(:millisecond)

ids = for i <- 1..n_ws, do: "WS-#{String.pad_leading(Integer.to_string(i), 4, "0")}"

endpoints =
  ids
  |> Enum.with_index()
  |> Enum.map(fn {id, i} ->
    wc = if i == 0, do: "tcp://127.0.0.1:0", else: "loopback:wc-#{id}"
    {:ok, _} = Vws.CEC.Workstation.start(id: id, wc: wc)
    id
  end)
  |> Enum.map(wait_listening)

started_s = (System.monotonic_time(:millisecond) - t_start) / 1000
mem1 = :erlang.memory(:total)
procs = length(Process.list())

# every poller connects first, then all start together at random phases
now = System.monotonic_time(:millisecond) + 500
stop = now + seconds * 1_000
parent = self()

# two bare echoes (TCP, loopback) polled the same way: the floor under this load
floor_endpoints = [echo.("tcp://127.0.0.1:0"), echo.("loopback:echo-many")]

pollers =
  for {endpoint, i} <- Enum.with_index(endpoints ++ floor_endpoints) do
    spawn_link(fn ->
      conn = Raw.connect(endpoint)
      _ = Raw.exchange(conn, status)
      phase = :rand.uniform(poll_ms) - 1
      lines = :persistent_term.get({:wc_turnaround, :statuses})
      send(parent, {:result, i, Raw.poll(conn, lines, now + phase, poll_ms, stop)})
    end)
  end

# the BEAM's CPU time and its schedulers' utilisation over the polling
Process.sleep(max(now - System.monotonic_time(:millisecond), 0))
{cpu0, _} = :erlang.statistics(:runtime)
util0 = :scheduler.sample()

results =
  for _ <- pollers, into: %{} do
    receive do
      {:result, i, list} -> {i, list}
    after
      seconds * 1_000 + 60_000 -> raise "a poller did not finish"
    end
  end

{cpu1, _} = :erlang.statistics(:runtime)
total_util = Bench.normal_utilization(util0)

floor_tcp_many = Enum.reject(results[n_ws], &(&1 == :timeout))
floor_lo_many = Enum.reject(results[n_ws + 1], &(&1 == :timeout))
results = Map.drop(results, [n_ws, n_ws + 1])

{tcp_many, lo_many} =
  Enum.reduce(results, {[], []}, fn
    {0, list}, {t, l} -> {list ++ t, l}
    {_, list}, {t, l} -> {t, list ++ l}
  end)

timeouts = Enum.count(tcp_many ++ lo_many, &(&1 == :timeout))
tcp_many = Enum.reject(tcp_many, &(&1 == :timeout))
lo_many = Enum.reject(lo_many, &(&1 == :timeout))
exchanges = length(tcp_many) + length(lo_many)

fmt = fn x -> "#{round(x)}" end
p99 = fn list -> Bench.pct(list, 0.99) end

verdict = fn list, target ->
  p = p99.(list)
  Bench.verdict(p <= target, "#{round(p - target)} µs (p99 #{round(p)} µs)")
end

# against the floor measured beside it: p99 ≤ 1.5 × the echo's p99
ratio = fn list, floor ->
  r = p99.(list) / max(p99.(floor), 1)

  "#{:erlang.float_to_binary(r, decimals: 2)}× the floor's p99 (#{round(p99.(list))} / #{round(p99.(floor))} µs): " <>
    Bench.verdict(r <= 1.5, "#{round(p99.(list) - 1.5 * p99.(floor))} µs")
end

IO.puts(
  Enum.join(
    ["WC turnaround (status string → first byte of the reply, raw client round trip)" | machine] ++
      [
        "  string         #{String.trim(status)} → 13S0001#{"0000NONE"}…, #{byte_size(status)} bytes in",
        "  alone (2 workstations on the node, one on TCP, one on loopback; every 2 ms one string to each and to each echo, in turn; #{samples} samples)",
        "    TCP          µs  #{Bench.summary(alone_tcp, fmt)}",
        "    loopback     µs  #{Bench.summary(alone_lo, fmt)}",
        "    floor, TCP   µs  #{Bench.summary(floor_tcp, fmt)}   (the same exchange with a bare echo process:",
        "    floor, loop. µs  #{Bench.summary(floor_lo, fmt)}    what the machine and the transport cost alone)",
        "    target       p99 ≤ 100 µs: TCP #{verdict.(alone_tcp, 100)}, loopback #{verdict.(alone_lo, 100)}",
        "    vs floor     p99 ≤ 1.5× the echo's, sample by sample beside it: TCP #{ratio.(alone_tcp, floor_tcp)}; loopback #{ratio.(alone_lo, floor_lo)}",
        "  #{n_ws} workstations on the node (started in #{Float.round(started_s, 1)} s, #{procs} processes, #{Bench.mb(mem1 - mem0)} MB),",
        "  each polled every #{poll_ms} ms by its own raw WC for #{seconds} s: #{Bench.thousands(exchanges / seconds)} strings/s in all",
        "    loopback     µs  #{Bench.summary(lo_many, fmt)}   (#{Bench.thousands(length(lo_many))} exchanges, #{n_ws - 1} workstations)",
        "    TCP          µs  #{Bench.summary(tcp_many, fmt)}   (#{length(tcp_many)} exchanges, 1 workstation)",
        "    floor        µs  TCP #{Bench.summary(floor_tcp_many, fmt)}, loopback #{Bench.summary(floor_lo_many, fmt)}   (bare echoes polled alike, under this load)",
        "    vs floor     TCP #{ratio.(tcp_many, floor_tcp_many)}; loopback #{ratio.(lo_many, floor_lo_many)}",
        "    no reply     #{timeouts} within 5 s",
        "    CPU          #{round((cpu1 - cpu0) * 1_000 / max(exchanges, 1))} µs of BEAM CPU time per exchange (client, loopback pair, SUN_COMM); schedulers #{round(total_util * 100)} % busy",
        "    target       p99 ≤ 1 ms (one character at 9600 Bd): loopback #{verdict.(lo_many, 1_000)}, TCP #{verdict.(tcp_many, 1_000)}"
      ],
    "\n"
  )
)
