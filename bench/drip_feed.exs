# Drip feed (DNC E, download and execute): 1 MiB of short NC blocks streamed CEC → simulated
# GE-2000 while the machine runs it out of its block buffer, the line paced at 4800 Bd — in the
# simulator's time scale: the line's baud rate, the machine's feed rate and the CEC's WACK wait
# all run `--time-scale` times faster, and every figure is given in the machine's time (wall
# time × scale).
#
#     mix run bench/drip_feed.exs [--size BYTES] [--baud BD] [--time-scale N] [--memory BYTES]
#                                 [--feed-share F] [--block BYTES]
#
# The machine runs the program at `--feed-share` (default 0.98, the goal) of the line's limit:
# the text bytes a second the half-duplex line carries stop-and-wait with zero turnaround time
# (every character of every block, acknowledgement, bid and EOT, 10 bits each). Figures:
# achieved throughput as a share of that limit (over the time the machine did not hold the
# line with WACK, and overall), and whether the machine's buffer ever ran empty.
#
# Run by hand (1 MiB at 4800 Bd is 37 minutes of line time: ~3.7 min at the default ×10).

Code.require_file("support.exs", __DIR__)
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
      feed_share: :float,
      block: :integer
    ]
  )

size = Keyword.get(opts, :size, 1_048_576)
baud = Keyword.get(opts, :baud, 4_800)
scale = Keyword.get(opts, :time_scale, 10)
memory = Keyword.get(opts, :memory, 8_192)
share = Keyword.get(opts, :feed_share, 0.98)
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
feed_rate = round(limit_rate * share)

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

# time the machine held the line with WACK: from a WACK to the next block sent
bench = self()

Vws.Telemetry.attach_many(
  "drip-bench",
  [[:vws, :dnc, :pause], [:vws, :dnc, :block_sent]],
  fn
    [:vws, :dnc, :pause], _, %{kind: :wack_received, role: :cec}, _ ->
      send(bench, {:wack, System.monotonic_time()})

    [:vws, :dnc, :block_sent], _, %{role: :cec}, _ ->
      send(bench, {:sent, System.monotonic_time()})

    _, _, _, _ ->
      :ok
  end,
  nil
)

t0 = System.monotonic_time()
{:ok, []} = DNC.request(cec, command, blocks)
wall_s = System.convert_time_unit(System.monotonic_time() - t0, :native, :microsecond) / 1.0e6

paused_native =
  Stream.repeatedly(fn ->
    receive do
      msg -> msg
    after
      0 -> nil
    end
  end)
  |> Enum.take_while(& &1)
  |> Enum.reduce({0, nil}, fn
    {:wack, t}, {sum, nil} -> {sum, t}
    {:wack, _t}, {sum, since} -> {sum, since}
    {:sent, t}, {sum, since} when since != nil -> {sum + t - since, nil}
    {:sent, _}, acc -> acc
  end)
  |> elem(0)

paused_s = System.convert_time_unit(paused_native, :native, :microsecond) / 1.0e6

Stream.repeatedly(fn ->
  Process.sleep(20)
  GE2000.drip(sim)
end)
|> Enum.find(&(&1.state in [:done, :broken]))

drip = GE2000.drip(sim)
counters = DNC.info(cec).counters

elapsed_s = wall_s * scale
sending_s = (wall_s - paused_s) * scale
share_sending = limit_s / sending_s * 100
share_all = byte_size(text) / elapsed_s / limit_rate * 100

IO.puts("""
DNC drip feed benchmark (E, download and execute)
#{Enum.join(Vws.Bench.machine(), "\n")}
  line           #{baud} Bd, #{char_bits} bits a character (8N1), paced by the simulator at ×#{scale} (#{baud * scale} Bd wall)
  program        #{byte_size(text)} bytes, #{length(lines)} NC blocks (#{Float.round(byte_size(text) / length(lines), 1)} characters each), #{length(blocks)} text blocks of at most #{block} bytes (CRC)
  machine        buffer #{memory} bytes, runs the program at #{feed_rate} characters/s (#{share * 100} % of the line's limit)
  line limit     #{Float.round(limit_s, 1)} s for #{chars} characters (stop-and-wait, zero turnaround): #{Float.round(limit_rate, 1)} program bytes/s
  measured       #{Float.round(elapsed_s, 1)} s (#{Float.round(wall_s, 1)} s wall), of which #{Float.round(paused_s * scale, 1)} s held by the machine's WACKs (#{counters.wacks_received} WACKs)
  throughput     #{Float.round(share_sending, 2)} % of the line's limit while the CEC could send (goal ≥ 98 %: #{if share_sending >= 98.0, do: "MET", else: "MISSED"}); #{Float.round(share_all, 2)} % overall
  buffer         ran empty #{drip.underruns} times (#{drip.starved_ms * scale} ms in all, machine time) — #{if drip.underruns == 0, do: "never empty: MET", else: "MISSED"}; at most #{drip.max_fill} of #{memory} bytes
  exact          #{drip.state == :done and drip.received == byte_size(text) and drip.crc == Vws.Codecs.CRC16.compute(text)} (#{drip.received} bytes received, #{drip.ran} run, CRC #{Integer.to_string(drip.crc, 16)})
  retries        #{counters.retransmissions} retransmissions, #{counters.enqs_sent - 1} ENQ polls
""")
