# Hostile HTTP clients and an honest one (issue 30): is the honest client served within 1 s, and the
# WC link unaffected, while --hostile sockets (idle, trickling, abandoned MTConnect streams) come
# and go?
#
#     mix run bench/http_hostile.exs [--hostile 2000] [--seconds 20] [--samples 2000] [--nice]
#
# This node runs one workstation (SUN_COMM on TCP 127.0.0.1) and the web server with its default
# limits (1,024 connections, 64 per client, 10 new connections/s per client while it is half
# full, 50 requests/s per client, 500 in all). The hostile
# sockets come from a separate OS process (`elixir`, plain gen_tcp), spread over 40 loopback source
# addresses (127.0.0.10–49, 50 each: together more than the server's 1,024 connections), each in
# a bounded loop that stops at the deadline by itself:
#
#   * idle (35 %): connect and send nothing; when closed, connect again 100 ms later;
#   * trickling (35 %): connect, send a request line a byte a second, never ending it; again;
#   * abandoned streams (30 %): `GET /current?interval=10000` (or `/sample?interval=10000`), read
#     the answer's head, close, and again 100 ms later.
#
# Meanwhile, from 127.0.0.2, the honest client asks `GET /current` and `GET /api/state` on a fresh
# connection each, one every 250 ms, timing each from connect to the last byte; and a raw WC
# (gen_tcp, passive, nodelay) sends `*0001*S0001ROBOT_CMD*…` every 2 ms, timing send → reply, as in
# bench/http_load.exs. With --nice the hostile process runs at nice 19 (as if on other hosts).
# Only loopback addresses are used. The file descriptors: the hostile process holds up to
# --hostile sockets, the node up to 1,024 + a few; `ulimit -n` must allow it (checked below).

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [hostile: :integer, seconds: :integer, samples: :integer, nice: :boolean]
  )

hostile = Keyword.get(opts, :hostile, 2_000)
seconds = Keyword.get(opts, :seconds, 20)
samples = Keyword.get(opts, :samples, 2_000)
nice = Keyword.get(opts, :nice, false)
machine = Bench.machine()

{ulimit, 0} = System.cmd("sh", ["-c", "ulimit -n"])
ulimit = ulimit |> String.trim() |> String.to_integer()

if ulimit < hostile + 1_200 do
  IO.puts(
    "ulimit -n is #{ulimit}: run as `sh -c 'ulimit -n #{hostile + 2_000} && mix run bench/http_hostile.exs'`"
  )

  System.halt(1)
end

{:ok, _} = Vws.CEC.Workstation.start(id: "HOSTILE", wc: "tcp://127.0.0.1:0", devices: [])

wc_port =
  Enum.find_value(1..500, fn _ ->
    Process.sleep(10)
    endpoint = Vws.CEC.SunComm.listening("HOSTILE")
    endpoint && endpoint.port
  end)

{:ok, web} = Vws.Ops.Web.start(port: 0)
http_port = Vws.Ops.Web.port(web)

status =
  %Vws.Codecs.WC.CommandString{
    sequence: 1,
    commands: [%Vws.Codecs.WC.Command{letter: "S", set: :status, number: 1, text: "ROBOT_CMD"}]
  }
  |> Vws.Codecs.WC.CommandString.encode()
  |> IO.iodata_to_binary()

{:ok, wc} =
  :gen_tcp.connect({127, 0, 0, 1}, wc_port, [:binary, active: false, nodelay: true, packet: :line])

# µs from the send to the reply line, `n` times, one every 2 ms
measure = fn n ->
  for _ <- 1..n do
    t0 = System.monotonic_time()
    :ok = :gen_tcp.send(wc, status)
    {:ok, _line} = :gen_tcp.recv(wc, 0, 10_000)
    t1 = System.monotonic_time()
    Process.sleep(2)
    System.convert_time_unit(t1 - t0, :native, :nanosecond) / 1_000
  end
end

wc_summary = fn label, us ->
  :io_lib.format("  ~-34s p50 ~8.1f µs   p99 ~8.1f µs   max ~9.1f µs   (~B samples)", [
    label,
    Bench.pct(us, 0.5),
    Bench.pct(us, 0.99),
    Enum.max(us),
    length(us)
  ])
  |> IO.iodata_to_binary()
end

# One honest GET on a fresh connection from 127.0.0.2: {status or error, ms from connect to the end}
honest_get = fn path ->
  t0 = System.monotonic_time(:microsecond)

  result =
    with {:ok, s} <-
           :gen_tcp.connect(
             {127, 0, 0, 1},
             http_port,
             [:binary, active: false, ip: {127, 0, 0, 2}],
             30_000
           ),
         :ok <-
           :gen_tcp.send(s, "GET #{path} HTTP/1.1\r\nhost: bench\r\nconnection: close\r\n\r\n") do
      read = fn read, acc ->
        case :gen_tcp.recv(s, 0, 30_000) do
          {:ok, data} ->
            read.(read, acc <> data)

          {:error, :closed} ->
            {:ok, acc}

          {:error, e} ->
            {:error, e}
        end
      end

      answer = read.(read, "")
      :gen_tcp.close(s)

      case answer do
        {:ok, "HTTP/1.1 " <> <<code::binary-size(3), _::binary>>} -> String.to_integer(code)
        {:ok, _} -> :no_answer
        {:error, e} -> e
      end
    else
      {:error, e} -> e
    end

  {result, (System.monotonic_time(:microsecond) - t0) / 1000}
end

_warm = measure.(200)
idle = measure.(samples)
honest_idle = for path <- ["/current", "/api/state"], _ <- 1..10, do: honest_get.(path)

generator = ~S"""
[port, total, seconds] = System.argv() |> Enum.map(&String.to_integer/1)
deadline = System.monotonic_time(:millisecond) + seconds * 1000
parent = self()
live? = fn -> System.monotonic_time(:millisecond) < deadline end

connect = fn i ->
  :gen_tcp.connect({127, 0, 0, 1}, port,
    [:binary, active: false, ip: {127, 0, 0, 10 + rem(i, 40)}], 5_000)
end

# waits until the server closes the socket or the deadline: true if closed by the server
closed? = fn s, wait ->
  case :gen_tcp.recv(s, 0, wait) do
    {:error, :closed} -> true
    {:error, :econnreset} -> true
    {:error, :timeout} -> false
    {:ok, _} -> false
  end
end

idle = fn idle, i, c ->
  if live?.() do
    case connect.(i) do
      {:ok, s} ->
        left = max(deadline - System.monotonic_time(:millisecond), 0)
        c = if closed?.(s, left), do: Map.update(c, :idle_closed, 1, &(&1 + 1)), else: c
        :gen_tcp.close(s)
        Process.sleep(100)
        idle.(idle, i, Map.update(c, :idle_connects, 1, &(&1 + 1)))
      {:error, _} ->
        Process.sleep(100)
        idle.(idle, i, Map.update(c, :connect_errors, 1, &(&1 + 1)))
    end
  else
    c
  end
end

trickle_on = fn trickle_on, s, bytes ->
  cond do
    not live?.() -> :deadline
    :gen_tcp.send(s, binary_part(bytes, 0, 1)) != :ok -> :closed
    closed?.(s, 1_000) -> :closed
    true -> trickle_on.(trickle_on, s, binary_part(bytes, 1, byte_size(bytes) - 1) <> "a")
  end
end

trickle = fn trickle, i, c ->
  if live?.() do
    case connect.(i) do
      {:ok, s} ->
        c = Map.update(c, :trickle_connects, 1, &(&1 + 1))
        c = case trickle_on.(trickle_on, s, "GET /api/state?x=aaaaaaaa") do
          :closed -> Map.update(c, :trickle_closed, 1, &(&1 + 1))
          :deadline -> c
        end
        :gen_tcp.close(s)
        Process.sleep(100)
        trickle.(trickle, i, c)
      {:error, _} ->
        Process.sleep(100)
        trickle.(trickle, i, Map.update(c, :connect_errors, 1, &(&1 + 1)))
    end
  else
    c
  end
end

stream = fn stream, i, c ->
  if live?.() do
    path = if rem(i, 2) == 0, do: "/current?interval=10000", else: "/sample?interval=10000"
    c =
      with {:ok, s} <- connect.(i),
           :ok <- :gen_tcp.send(s, "GET #{path} HTTP/1.1\r\nhost: x\r\n\r\n"),
           :ok <- :inet.setopts(s, packet: :http_bin),
           {:ok, {:http_response, _, code, _}} <- :gen_tcp.recv(s, 0, 15_000) do
        :gen_tcp.close(s)
        Map.update(c, {:stream, code}, 1, &(&1 + 1))
      else
        _ -> Map.update(c, :stream_errors, 1, &(&1 + 1))
      end
    Process.sleep(100)
    stream.(stream, i, c)
  else
    c
  end
end

for i <- 1..total do
  kind = rem(i, 20)
  spawn(fn ->
    c = cond do
      kind < 7 -> idle.(idle, i, %{})
      kind < 14 -> trickle.(trickle, i, %{})
      true -> stream.(stream, i, %{})
    end
    send(parent, {:counts, c})
  end)
end

total_counts =
  Enum.reduce(1..total, %{}, fn _, acc ->
    receive do
      {:counts, c} -> Map.merge(acc, c, fn _, a, b -> a + b end)
    end
  end)

IO.puts("COUNTS " <> inspect(total_counts))
"""

script =
  Path.join(System.tmp_dir!(), "vws_http_hostile_#{System.unique_integer([:positive])}.exs")

File.write!(script, generator)
gen_args = [script, "#{http_port}", "#{hostile}", "#{seconds}"]

{gen_exe, gen_args} =
  if nice,
    do:
      {System.find_executable("nice"), ["-n", "19", System.find_executable("elixir") | gen_args]},
    else: {System.find_executable("elixir"), gen_args}

gen =
  Port.open({:spawn_executable, gen_exe}, [
    :binary,
    :exit_status,
    :stderr_to_stdout,
    args: gen_args
  ])

# the hostile sockets connect (the elixir VM starts in about a second); then, while they last:
# the honest client, the WC, and the server's connection count, all at once
Process.sleep(3_000)
window = (seconds - 5) * 1000
parent = self()

spawn_link(fn ->
  stop = System.monotonic_time(:millisecond) + window

  results =
    Stream.repeatedly(fn ->
      r = for path <- ["/current", "/api/state"], do: Tuple.append(honest_get.(path), path)
      Process.sleep(250)
      r
    end)
    |> Enum.reduce_while([], fn r, acc ->
      if System.monotonic_time(:millisecond) < stop,
        do: {:cont, r ++ acc},
        else: {:halt, r ++ acc}
    end)

  send(parent, {:honest, results})
end)

spawn_link(fn ->
  stop = System.monotonic_time(:millisecond) + window

  seen =
    Stream.repeatedly(fn ->
      Process.sleep(100)
      web |> Vws.Ops.Web.connections() |> elem(0)
    end)
    |> Enum.reduce_while([], fn n, acc ->
      if System.monotonic_time(:millisecond) < stop,
        do: {:cont, [n | acc]},
        else: {:halt, [n | acc]}
    end)

  send(parent, {:connections, seen})
end)

loaded = measure.(min(samples, div(window, 3)))
honest = receive(do: ({:honest, r} -> r))
connections = receive(do: ({:connections, c} -> c))

output =
  Stream.repeatedly(fn ->
    receive do
      {^gen, {:data, data}} -> data
      {^gen, {:exit_status, _}} -> :eof
    after
      (seconds + 60) * 1000 -> :eof
    end
  end)
  |> Enum.take_while(&(&1 != :eof))
  |> Enum.join()

File.rm(script)

counts =
  case Regex.run(~r/COUNTS (.*)/, output) do
    [_, c] -> c
    nil -> "(the generator said: #{String.slice(output, 0, 500)})"
  end

# after the hostile process is gone: every connection closed?
Process.sleep(2_000)
{left, _} = Vws.Ops.Web.connections(web)

honest_summary = fn label, results ->
  ms = Enum.map(results, &elem(&1, 1))
  statuses = Enum.frequencies(Enum.map(results, &elem(&1, 0)))
  over = Enum.count(ms, &(&1 > 1_000))

  :io_lib.format(
    "  ~-34s p50 ~8.1f ms   p99 ~8.1f ms   max ~9.1f ms   ~B answers ~s, ~B over 1 s",
    [
      label,
      Bench.pct(ms, 0.5),
      Bench.pct(ms, 0.99),
      Enum.max(ms),
      length(ms),
      inspect(statuses),
      over
    ]
  )
  |> IO.iodata_to_binary()
end

IO.puts("""
Hostile HTTP clients, an honest one and the WC link (bench/http_hostile.exs)
#{Enum.join(machine, "\n")}
  hostile        #{hostile} sockets from 40 loopback addresses (idle 35 %, trickling 35 %, abandoned streams 30 %), #{seconds} s, a separate OS process#{if nice, do: " at nice 19", else: ""}
  hostile saw    #{counts}
  server         connections open during the window: max #{Enum.max(connections)}, p50 #{Bench.pct(connections, 0.5)}; #{left} left 2 s after the hostile process ended
#{honest_summary.("honest GET, HTTP idle", honest_idle)}
#{honest_summary.("honest GET, #{hostile} hostile", honest)}
#{honest_summary.("  of which /current", Enum.filter(honest, &(elem(&1, 2) == "/current")))}
#{honest_summary.("  of which /api/state", Enum.filter(honest, &(elem(&1, 2) == "/api/state")))}
#{wc_summary.("WC status, HTTP idle", idle)}
#{wc_summary.("WC status, #{hostile} hostile", loaded)}
""")
