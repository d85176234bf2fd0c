# WC turnaround: a status string sent to SUN_COMM, timed from the moment its last byte is
# handed to the transport until the first byte of the reply arrives — by a raw client (no
# Vws.Peers.WC.Client, no script runner), with monotonic time, right at the socket or loopback pair.
#
#     mix run bench/wc_turnaround.exs [--samples 2000] [--workstations 1000] [--poll-ms 100] [--seconds 10]
#
# 1. One workstation alone on the node: a raw TCP client (gen_tcp, passive, nodelay) and a raw
#    loopback client, each sending `*0001*S0001ROBOT_CMD*…` every 2 ms, --samples times.
# 2. --workstations on the node (loopback endpoints, no sockets), each with its own raw WC
#    polling ROBOT_CMD every --poll-ms (the WC client's polling interval), at random phases,
#    for --seconds; one of them is served on TCP instead and polled the same way.
#
# The time measured is the client's round trip: it includes the transport both ways, so it is
# an upper bound of SUN_COMM's own turnaround (last byte in → first byte out). Targets: p99 ≤
# 100 µs alone, ≤ 1 ms (one character time at 9600 Bd) with 1,000 workstations.

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

status =
  %Vws.Codecs.WC.CommandString{
    sequence: 1,
    commands: [%Vws.Codecs.WC.Command{letter: "S", set: :status, number: 1, text: "ROBOT_CMD"}]
  }
  |> Vws.Codecs.WC.CommandString.encode()
  |> IO.iodata_to_binary()

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

  # Polls every `period` ms on an absolute schedule from `start` (monotonic ms) until `stop`.
  def poll(conn, line, start, period, stop, acc \\ []) do
    now = System.monotonic_time(:millisecond)

    cond do
      start >= stop ->
        acc

      start > now ->
        Process.sleep(start - now)
        poll(conn, line, start, period, stop, acc)

      true ->
        poll(conn, line, start + period, period, stop, [exchange(conn, line) | acc])
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

alone = fn endpoint ->
  conn = Raw.connect(endpoint)
  # warm up
  for _ <- 1..100, do: Raw.exchange(conn, status)

  for _ <- 1..samples do
    Process.sleep(2)
    Raw.exchange(conn, status)
  end
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
alone_tcp = alone.(tcp_ep)
Vws.CEC.Workstation.stop("ALONE-TCP")
lo_ep = start_ws.("ALONE-LO", "loopback:alone")
alone_lo = alone.(lo_ep)
Vws.CEC.Workstation.stop("ALONE-LO")
floor_tcp = alone.(echo.("tcp://127.0.0.1:0"))
floor_lo = alone.(echo.("loopback:echo"))

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

pollers =
  for {endpoint, i} <- Enum.with_index(endpoints) do
    spawn_link(fn ->
      conn = Raw.connect(endpoint)
      _ = Raw.exchange(conn, status)
      phase = :rand.uniform(poll_ms) - 1
      send(parent, {:result, i, Raw.poll(conn, status, now + phase, poll_ms, stop)})
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

IO.puts(
  Enum.join(
    ["WC turnaround (status string → first byte of the reply, raw client round trip)" | machine] ++
      [
        "  string         #{String.trim(status)} → 13S0001#{"0000NONE"}…, #{byte_size(status)} bytes in",
        "  alone (1 workstation on the node, one string every 2 ms, #{samples} samples)",
        "    TCP          µs  #{Bench.summary(alone_tcp, fmt)}",
        "    loopback     µs  #{Bench.summary(alone_lo, fmt)}",
        "    floor, TCP   µs  #{Bench.summary(floor_tcp, fmt)}   (the same exchange with a bare echo process:",
        "    floor, loop. µs  #{Bench.summary(floor_lo, fmt)}    what the machine and the transport cost alone)",
        "    target       p99 ≤ 100 µs: TCP #{verdict.(alone_tcp, 100)}, loopback #{verdict.(alone_lo, 100)}",
        "  #{n_ws} workstations on the node (started in #{Float.round(started_s, 1)} s, #{procs} processes, #{Bench.mb(mem1 - mem0)} MB),",
        "  each polled every #{poll_ms} ms by its own raw WC for #{seconds} s: #{Bench.thousands(exchanges / seconds)} strings/s in all",
        "    loopback     µs  #{Bench.summary(lo_many, fmt)}   (#{Bench.thousands(length(lo_many))} exchanges, #{n_ws - 1} workstations)",
        "    TCP          µs  #{Bench.summary(tcp_many, fmt)}   (#{length(tcp_many)} exchanges, 1 workstation)",
        "    no reply     #{timeouts} within 5 s",
        "    CPU          #{round((cpu1 - cpu0) * 1_000 / max(exchanges, 1))} µs of BEAM CPU time per exchange (client, loopback pair, SUN_COMM); schedulers #{round(total_util * 100)} % busy",
        "    target       p99 ≤ 1 ms (one character at 9600 Bd): loopback #{verdict.(lo_many, 1_000)}, TCP #{verdict.(tcp_many, 1_000)}"
      ],
    "\n"
  )
)
