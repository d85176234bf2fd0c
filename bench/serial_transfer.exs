# A 64 KB NC program at 4800 Bd on the plain RS-232 port (Vws.Links.RS232, profile
# rs232-xonxoff) to the simulated control (Vws.Sim.RS232Control), three ways:
#
#   raw       over TCP, the control faster than the line (no XOFF ever): the line's own time
#   rfc2217   the same through ser2net's RFC 2217 accepter in front of a pty pair (the CEC sets
#             the port to 4800 Bd; the control opens the other pty)
#   xonxoff   over TCP, the control 2 % slower than the line with a 256-byte buffer: it stops
#             the CEC with XOFF over and over; timed against the control's own limit
#
# Each is timed against its limit: the line's (65,536 bytes × 10 bits / 4800 Bd = 136.5 s), or
# the control's (bytes / its rate). Every transfer must arrive byte-exact (the control's kept
# program is compared), with no byte dropped.
#
#     nice -n 15 mix run bench/serial_transfer.exs [--size BYTES] [--baud BD] [--only raw,rfc2217,xonxoff]
#
# Run by hand: it takes the time the line takes, about 7 minutes for the three.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :warning)

alias Vws.Links.RS232
alias Vws.Links.DNC.Frame.Command
alias Vws.Sim.RS232Control

{opts, _, _} =
  OptionParser.parse(System.argv(), strict: [size: :integer, baud: :integer, only: :string])

size = Keyword.get(opts, :size, 65_536)
baud = Keyword.get(opts, :baud, 4_800)
only = String.split(Keyword.get(opts, :only, "raw,rfc2217,xonxoff"), ",")
cps = div(baud, 10)

# An NC program of exactly `size` bytes, O4711 (LF lines; CR LF on the wire adds a byte a line)
lines =
  Stream.iterate(1, &(&1 + 1))
  |> Stream.map(&"N#{&1 * 5} G01 X#{rem(&1 * 37, 1000)}.#{rem(&1, 10)} Y-#{rem(&1 * 11, 500)}.25")
  |> Enum.reduce_while({["O4711", "%"], 8}, fn line, {acc, bytes} ->
    if bytes + byte_size(line) + 1 >= size - 2,
      do: {:halt, {["%", String.duplicate("9", max(size - bytes - 3, 0)) | acc], size}},
      else: {:cont, {[line | acc], bytes + byte_size(line) + 1}}
  end)
  |> elem(0)
  |> Enum.reverse()

text = Vws.Links.DNC.Program.to_text(lines)
{:ok, framing} = Vws.Links.RS232.Framing.new(eol: :lf)
wire_bytes = IO.iodata_to_binary(Vws.Links.RS232.Framing.encode(text, framing)) |> byte_size()
send_cmd = %Command{direction: :send, operation: :part_program}

run = fn name, endpoint, sim, limit_s, limit_what ->
  {:ok, link} =
    RS232.start_link(
      endpoint: endpoint,
      baud: baud,
      framing: [eol: :lf],
      verify: :none,
      owner: self()
    )

  receive do
    {:dnc, ^link, :connected} -> :ok
  after
    10_000 -> raise "#{name}: the link did not connect"
  end

  t0 = System.monotonic_time(:microsecond)
  {:ok, []} = RS232.request(link, send_cmd, [text], :infinity)
  sent_s = (System.monotonic_time(:microsecond) - t0) / 1.0e6

  # the control has the whole program once its buffer has run empty
  wait = fn wait ->
    info = RS232Control.info(sim)
    if info.programs["004711.PRO"] == text, do: info, else: Process.sleep(5) && wait.(wait)
  end

  info = wait.(wait)
  total_s = (System.monotonic_time(:microsecond) - t0) / 1.0e6
  link_info = RS232.info(link)
  GenServer.stop(link)

  IO.puts(
    "  #{String.pad_trailing(name, 9)} #{:erlang.float_to_binary(total_s, decimals: 3)} s " <>
      "(all sent after #{:erlang.float_to_binary(sent_s, decimals: 3)} s) vs #{limit_what} " <>
      "#{:erlang.float_to_binary(limit_s, decimals: 3)} s: " <>
      "#{:erlang.float_to_binary((total_s / limit_s - 1) * 100, decimals: 2)} %; " <>
      "XOFF #{link_info.xoffs}, dropped #{info.dropped}, byte-exact #{info.programs["004711.PRO"] == text}"
  )
end

IO.puts("RS-232 port, #{size}-byte program (#{wire_bytes} bytes on the wire) at #{baud} Bd")
Enum.each(Vws.Bench.machine(), &IO.puts/1)
line_limit = wire_bytes / cps

if "raw" in only do
  {:ok, sim} = RS232Control.start_link(buffer: 4096, rate: cps * 4)
  run.("raw", RS232Control.endpoint(sim) <> "", sim, line_limit, "line limit")
  GenServer.stop(sim)
end

if "rfc2217" in only do
  dir = Path.join(System.tmp_dir!(), "vws-bench-#{System.unique_integer([:positive])}")
  File.mkdir_p!(dir)
  a = Path.join(dir, "a")
  b = Path.join(dir, "b")

  cable =
    Port.open({:spawn_executable, System.find_executable("socat")}, [
      :binary,
      args: ["pty,raw,echo=0,link=#{a}", "pty,raw,echo=0,link=#{b}"]
    ])

  Enum.find(1..200, fn _ -> Process.sleep(25) && File.exists?(a) && File.exists?(b) end) ||
    raise "socat made no pty pair"

  {:ok, l} = :gen_tcp.listen(0, ip: {127, 0, 0, 1})
  {:ok, port} = :inet.port(l)
  :gen_tcp.close(l)
  config = Path.join(dir, "ser2net.yaml")

  File.write!(config, """
  connection: &bench
    accepter: telnet(rfc2217),tcp,127.0.0.1,#{port}
    connector: serialdev,#{a},9600n81,local
    options:
      kickolduser: true
  """)

  ser2net = System.find_executable("ser2net") || "/usr/sbin/ser2net"

  server =
    Port.open({:spawn_executable, ser2net},
      args: ["-n", "-d", "-c", config, "-P", Path.join(dir, "pid")]
    )

  Enum.find(1..200, fn _ ->
    Process.sleep(25)

    case :gen_tcp.connect({127, 0, 0, 1}, port, [], 100) do
      {:ok, probe} -> :gen_tcp.close(probe) == :ok
      _ -> false
    end
  end) || raise "ser2net did not listen"

  {:ok, sim} = RS232Control.start_link(tty: "tty:#{b}", buffer: 4096, rate: cps * 4)
  run.("rfc2217", "rfc2217://127.0.0.1:#{port}?baud=#{baud}", sim, line_limit, "line limit")
  {settings, 0} = System.cmd("stty", ["-F", a, "-a"])
  IO.puts("            (stty -F on the server's pty: #{Regex.run(~r/speed \d+ baud/, settings)})")
  GenServer.stop(sim)

  for p <- [server, cable] do
    {:os_pid, os_pid} = Port.info(p, :os_pid)
    System.cmd("kill", [Integer.to_string(os_pid)])
  end

  File.rm_rf!(dir)
end

if "xonxoff" in only do
  rate = div(cps * 98, 100)
  {:ok, sim} = RS232Control.start_link(buffer: 256, rate: rate)

  run.(
    "xonxoff",
    RS232Control.endpoint(sim),
    sim,
    wire_bytes / rate,
    "control limit (#{rate} cps)"
  )

  GenServer.stop(sim)
end
