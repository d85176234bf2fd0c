# The WC link under HTTP load (issue 16): WC status round-trip p99 on a node whose dashboard
# (`Vws.Ops.Web`) is idle, then while --clients concurrent HTTP clients hammer it.
#
#     mix run bench/http_load.exs [--clients 1000] [--samples 2000] [--seconds 20] [--path /api/state] [--nice]
#
# This node runs one workstation (SUN_COMM on TCP 127.0.0.1) and the web server. A raw WC (gen_tcp,
# passive, nodelay) sends `*0001*S0001ROBOT_CMD*…` every 2 ms and times send → first reply byte
# with monotonic time. The HTTP load comes from a separate OS process (`elixir`, plain gen_tcp):
# --clients connections, each sending GET --path on a kept-alive connection as fast as answers
# come, reconnecting when closed; it reports the answers it got by status. Both share the
# machine's cores with everything else; with --nice the generator runs at nice 19, standing in
# for clients on other hosts (which do not take the CEC's CPU).

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [
      clients: :integer,
      samples: :integer,
      seconds: :integer,
      path: :string,
      nice: :boolean
    ]
  )

clients = Keyword.get(opts, :clients, 1_000)
samples = Keyword.get(opts, :samples, 2_000)
seconds = Keyword.get(opts, :seconds, 20)
path = Keyword.get(opts, :path, "/api/state")
nice = Keyword.get(opts, :nice, false)
machine = Bench.machine()

{:ok, _} = Vws.CEC.Workstation.start(id: "HTTPLOAD", wc: "tcp://127.0.0.1:0", devices: [])

wc_port =
  Enum.find_value(1..500, fn _ ->
    Process.sleep(10)
    endpoint = Vws.CEC.SunComm.listening("HTTPLOAD")
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

# µs from the send to the reply line, `n` times, one every 2 ms
measure = Bench.wc_client(wc_port, status)

summary = fn label, us ->
  :io_lib.format("  ~-34s p50 ~8.1f µs   p99 ~8.1f µs   max ~9.1f µs   (~B samples)", [
    label,
    Bench.pct(us, 0.5),
    Bench.pct(us, 0.99),
    Enum.max(us),
    length(us)
  ])
  |> IO.iodata_to_binary()
end

_warm = measure.(200)
idle = measure.(samples)

# The load generator: its own OS process.
generator = ~S"""
defmodule H do
  def headers(socket, length, close) do
    case :gen_tcp.recv(socket, 0, 30_000) do
      {:ok, :http_eoh} -> {:ok, length, close}
      {:ok, {:http_header, _, :"Content-Length", _, v}} -> headers(socket, String.to_integer(v), close)
      {:ok, {:http_header, _, :Connection, _, v}} -> headers(socket, length, close or String.downcase(v) == "close")
      {:ok, {:http_header, _, _, _, _}} -> headers(socket, length, close)
      other -> {:error, other}
    end
  end
end

[port, clients, seconds, path] = System.argv()
port = String.to_integer(port)
clients = String.to_integer(clients)
deadline = System.monotonic_time(:millisecond) + String.to_integer(seconds) * 1000
request = "GET #{path} HTTP/1.1\r\nhost: bench\r\n\r\n"
parent = self()

client = fn client, socket, counts ->
  socket =
    socket ||
      case :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, packet: :http_bin], 10_000) do
        {:ok, s} -> s
        {:error, _} -> nil
      end

  cond do
    System.monotonic_time(:millisecond) > deadline ->
      send(parent, {:counts, counts})

    socket == nil ->
      Process.sleep(10)
      client.(client, nil, Map.update(counts, :connect_error, 1, &(&1 + 1)))

    true ->
      with :ok <- :gen_tcp.send(socket, request),
           {:ok, {:http_response, _, code, _}} <- :gen_tcp.recv(socket, 0, 30_000),
           {:ok, length, close} <- H.headers(socket, 0, false),
           :ok <- :inet.setopts(socket, packet: :raw),
           {:ok, _} <- (if length > 0, do: :gen_tcp.recv(socket, length, 30_000), else: {:ok, ""}),
           :ok <- :inet.setopts(socket, packet: :http_bin) do
        counts = Map.update(counts, code, 1, &(&1 + 1))
        if close, do: :gen_tcp.close(socket)
        client.(client, if(close, do: nil, else: socket), counts)
      else
        _ ->
          :gen_tcp.close(socket)
          client.(client, nil, Map.update(counts, :io_error, 1, &(&1 + 1)))
      end
  end
end

for _ <- 1..clients, do: spawn(fn -> client.(client, nil, %{}) end)

total =
  Enum.reduce(1..clients, %{}, fn _, acc ->
    receive do
      {:counts, c} -> Map.merge(acc, c, fn _, a, b -> a + b end)
    end
  end)

IO.puts("COUNTS " <> inspect(total))
"""

script = Path.join(System.tmp_dir!(), "vws_http_load_#{System.unique_integer([:positive])}.exs")
File.write!(script, generator)

gen_args = [script, "#{http_port}", "#{clients}", "#{seconds}", path]

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

# let the clients connect and the load settle, then measure while it lasts
Process.sleep(3_000)
loaded = measure.(min(samples, div((seconds - 5) * 1000, 3)))

output = Bench.port_output(gen, (seconds + 60) * 1000)

File.rm(script)

counts =
  case Regex.run(~r/COUNTS (.*)/, output) do
    [_, c] -> c
    nil -> "(the generator said: #{String.slice(output, 0, 500)})"
  end

IO.puts("""
HTTP load and the WC link (bench/http_load.exs): WC status round trip, raw TCP client
#{Enum.join(machine, "\n")}
  HTTP load      #{clients} concurrent clients, GET #{path} kept alive, #{seconds} s, from a separate OS process#{if nice, do: " at nice 19 (as if on other hosts)", else: ""}
#{summary.("WC status, HTTP idle", idle)}
#{summary.("WC status, #{clients} HTTP clients", loaded)}
  HTTP answers   #{counts}
""")
