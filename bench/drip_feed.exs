# Drip feed (DNC E, download and execute): 1 MiB of short NC blocks streamed CEC → GE-2000
# while the machine runs it out of its 8 KiB block buffer, the line at 4800 Bd, the machine
# running the program at 50 %, 90 % and 120 % of the line's rate (issue 27 item 5). The sender
# asks again after a WACK at the pace it learned from the machine (Vws.Links.DNC.Pace).
#
#     mix run bench/drip_feed.exs [--size BYTES] [--baud BD] [--memory BYTES] [--block BYTES]
#                                 [--shares 0.5,0.9,1.2] [--simulator [--time-scale N]]
#
# Two ways to run it:
#
#   * default — in simulated time: the two protocol cores (Vws.Links.DNC.Session, the code the
#     link processes run) back to back over the in-memory line of the tests
#     (test/support/dnc_wire.ex) paced at the baud rate, the machine behind one of them running
#     its buffer every 20 ms and starting once half of it is full, as Vws.Sim.GE2000 does. No
#     clock, no scheduler: the figures do not depend on the machine's load. Seconds of wall time.
#   * `--simulator` — the CEC's link process against the simulated GE-2000 (Vws.Sim.GE2000) over
#     its paced line, in the simulator's time scale (`--time-scale`, default ×10: the baud rate,
#     the feed rate and the WACK wait's cap run that much faster; figures in the machine's time).
#     1 MiB at 4800 Bd is 37 minutes of line time: about 4 minutes a share at ×10. Run niced.
#
# "The line's rate" is its limit for program bytes: the text bytes a second the half-duplex
# line carries stop-and-wait with zero turnaround time (every character of every block,
# acknowledgement, bid and EOT, 10 bits each). Throughput is the program's bytes over the time
# from the request to the machine having run its last byte, as a share of min(line, machine)
# (goal ≥ 95 %); an underrun is the buffer running empty while more of the program is to come
# (goal 0 when the machine is slower than the line).

Code.require_file("support.exs", __DIR__)

# the in-memory line of the tests (compiled already under MIX_ENV=test)
unless Code.ensure_loaded?(Vws.Test.DNCWire),
  do: Code.require_file("../test/support/dnc_wire.ex", __DIR__)

Logger.configure(level: :warning)

alias Vws.Links.DNC
alias Vws.Links.DNC.{Frame, Program}
alias Vws.Links.DNC.Frame.{Command, Text}
alias Vws.Sim.GE2000

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [
      size: :integer,
      baud: :integer,
      time_scale: :integer,
      memory: :integer,
      block: :integer,
      shares: :string,
      simulator: :boolean
    ]
  )

size = Keyword.get(opts, :size, 1_048_576)
baud = Keyword.get(opts, :baud, 4_800)
scale = Keyword.get(opts, :time_scale, 10)
memory = Keyword.get(opts, :memory, 8_192)

shares =
  opts
  |> Keyword.get(:shares, "0.5,0.9,1.2")
  |> String.split(",")
  |> Enum.map(&(Float.parse(&1) |> elem(0)))

block = Keyword.get(opts, :block, 256)
char_bits = 10

# Short NC blocks (~20 characters), numbered O4711, the closing % last.
body =
  Stream.iterate(1, &(&1 + 1))
  |> Stream.map(&"N#{&1} G01 X#{rem(&1 * 37, 1000)}.#{rem(&1, 10)}")
  |> Enum.reduce_while({[], 8}, fn line, {acc, bytes} ->
    if bytes + byte_size(line) + 1 >= size - 2,
      do: {:halt, {acc, bytes}},
      else: {:cont, {[line | acc], bytes + byte_size(line) + 1}}
  end)
  |> elem(0)
  |> Enum.reverse()

lines = ["%", "O4711"] ++ body ++ ["%"]
text = Program.to_text(lines)
blocks = Frame.split_text(text, block)

command = %Command{
  direction: :send,
  check: :crc,
  operation: :download_execute,
  text: "004711.PRO"
}

len = fn iodata -> IO.iodata_length(iodata) end

master =
  len.(Frame.encode(:enq)) + len.(Frame.encode(command)) +
    Enum.sum(Enum.map(blocks, &len.(Frame.encode(%Text{text: &1}, check: :crc, max_text: block)))) +
    len.(Frame.encode(:eot))

slave = len.(Frame.encode(:ack0)) * (2 + length(blocks))
chars = master + slave
# in the machine's time
limit_s = chars * char_bits / baud
limit_rate = byte_size(text) / limit_s

IO.puts("""
DNC drip feed benchmark (E, download and execute) — #{if opts[:simulator], do: "the simulated GE-2000, time scale ×#{scale}", else: "simulated time, the protocol cores back to back"}
#{Enum.join(Vws.Bench.machine(), "\n")}
  line           #{baud} Bd, #{char_bits} bits a character (8N1): #{div(baud, char_bits)} characters/s
  program        #{byte_size(text)} bytes, #{length(lines)} NC blocks (#{Float.round(byte_size(text) / length(lines), 1)} characters each), #{length(blocks)} text blocks of at most #{block} bytes (CRC)
  line's rate    #{Float.round(limit_s, 1)} s for #{chars} characters (stop-and-wait, zero turnaround): #{Float.round(limit_rate, 1)} program bytes/s
  machine        buffer #{memory} bytes, starts once #{div(memory, 2)} are in
""")

run_wire = fn feed_rate ->
  r =
    Vws.Test.DNCWire.run(
      command: command,
      blocks: blocks,
      receive_buffer: memory,
      feed: feed_rate,
      baud: baud,
      start_fill: div(memory, 2),
      tick_ms: 20,
      max_steps: 20_000_000
    )

  %{
    ok: r.reply == {:ok, []},
    exact: r.blocks == blocks,
    elapsed_s: r.drained_ms / 1000,
    underruns: r.underruns,
    starved_s: r.starved_ms / 1000,
    max_fill: r.max_fill,
    wacks: r.counters.wacks_received,
    enqs: r.counters.enqs_sent - 1,
    retransmissions: r.counters.retransmissions
  }
end

run_sim = fn feed_rate ->
  {:ok, sim} =
    GE2000.start_link(
      pace: baud * scale,
      memory: memory,
      feed_rate: feed_rate * scale,
      link: [max_text: block]
    )

  {:ok, cec} =
    DNC.start_link(
      endpoint: GE2000.endpoint(sim),
      max_text: block,
      wack_delay: max(div(2_000, scale), 1)
    )

  Stream.repeatedly(fn ->
    Process.sleep(10)
    DNC.info(cec).state
  end)
  |> Enum.find(&(&1 == :idle))

  t0 = System.monotonic_time()
  reply = DNC.request(cec, command, blocks)

  Stream.repeatedly(fn ->
    Process.sleep(20)
    GE2000.drip(sim)
  end)
  |> Enum.find(&(&1.state in [:done, :broken]))

  wall_s = System.convert_time_unit(System.monotonic_time() - t0, :native, :microsecond) / 1.0e6
  drip = GE2000.drip(sim)
  counters = DNC.info(cec).counters
  GenServer.stop(cec)
  GenServer.stop(sim)

  %{
    ok: reply == {:ok, []},
    exact:
      drip.state == :done and drip.received == byte_size(text) and
        drip.crc == Vws.Codecs.CRC16.compute(text),
    elapsed_s: wall_s * scale,
    underruns: drip.underruns,
    starved_s: drip.starved_ms * scale / 1000,
    max_fill: drip.max_fill,
    wacks: counters.wacks_received,
    enqs: counters.enqs_sent - 1,
    retransmissions: counters.retransmissions
  }
end

for share <- shares do
  feed_rate = round(limit_rate * share)
  r = if opts[:simulator], do: run_sim.(feed_rate), else: run_wire.(feed_rate)
  target = min(limit_rate, feed_rate * 1.0)
  throughput = byte_size(text) / r.elapsed_s
  pct = throughput / target * 100
  slower? = feed_rate < limit_rate

  IO.puts("""
    machine at #{round(share * 100)} % (#{feed_rate} characters/s)
      took         #{Float.round(r.elapsed_s, 1)} s to run the whole program; #{r.wacks} WACKs, #{r.enqs} ENQs, #{r.retransmissions} retransmissions
      throughput   #{Float.round(throughput, 1)} bytes/s = #{Float.round(pct, 2)} % of min(line, machine) #{Float.round(target, 1)} (goal ≥ 95 %: #{if pct >= 95.0, do: "MET", else: "MISSED"})
      buffer       ran empty #{r.underruns} times (#{Float.round(r.starved_s, 1)} s in all)#{if slower?, do: " (goal 0: #{if r.underruns == 0, do: "MET", else: "MISSED"})", else: " (the machine is faster than the line: it must wait)"}; at most #{r.max_fill} of #{memory} bytes
      exact        #{r.ok and r.exact}
  """)
end
