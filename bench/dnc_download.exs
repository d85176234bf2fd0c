# A 64 KB part-program download on the DNC Level 2 link, CEC → simulated GE-2000, with the line
# paced at 4800 Bd, timed against the line's stop-and-wait limit: every byte of every block,
# acknowledgement, bid and EOT on a half-duplex 8N1 line, with no turnaround time at all.
#
#     mix run bench/dnc_download.exs [--size BYTES] [--baud BD] [--block BYTES]
#
# Run by hand (it takes the time the line takes: about 2½ minutes at 4800 Bd).

Logger.configure(level: :warning)

alias Vws.Links.DNC
alias Vws.Links.DNC.{Frame, Program}
alias Vws.Links.DNC.Frame.{Command, Text}
alias Vws.Sim.GE2000

{opts, _, _} =
  OptionParser.parse(System.argv(), strict: [size: :integer, baud: :integer, block: :integer])

size = Keyword.get(opts, :size, 65_536)
baud = Keyword.get(opts, :baud, 4_800)
block = Keyword.get(opts, :block, 256)
char_bits = 10

# An NC program of exactly `size` bytes: numbered O4711, LF after every line.
lines =
  Stream.iterate(1, &(&1 + 1))
  |> Stream.map(
    &"N#{&1 * 5} G01 X#{rem(&1 * 37, 1000)}.#{rem(&1, 10)} Y-#{rem(&1 * 11, 500)}.25 F300"
  )
  # (the last line is the closing %: the GE-2000 files only a whole program, PROTOCOLS.md §2)
  |> Enum.reduce_while({["O4711"], 6}, fn line, {acc, bytes} ->
    if bytes + byte_size(line) + 1 >= size - 2,
      do: {:halt, {["%", String.duplicate("9", max(size - bytes - 3, 0)) | acc], size}},
      else: {:cont, {[line | acc], bytes + byte_size(line) + 1}}
  end)
  |> elem(0)
  |> Enum.reverse()

text = Program.to_text(lines)
^size = byte_size(text)
blocks = Frame.split_text(text, block)
command = %Command{direction: :send, check: :lrc, operation: :part_program}

# Characters on the line, both directions, exactly as the two ends send them.
len = fn iodata -> IO.iodata_length(iodata) end

master =
  len.(Frame.encode(:enq)) + len.(Frame.encode(command)) +
    Enum.sum(Enum.map(blocks, &len.(Frame.encode(%Text{text: &1}, max_text: block)))) +
    len.(Frame.encode(:eot))

slave = len.(Frame.encode(:ack0)) * (2 + length(blocks))
chars = master + slave
limit_s = chars * char_bits / baud

{:ok, sim} = GE2000.start_link(pace: baud, link: [max_text: block])
{:ok, cec} = DNC.start_link(endpoint: GE2000.endpoint(sim), max_text: block)

Stream.repeatedly(fn ->
  Process.sleep(10)
  DNC.info(cec).state
end)
|> Enum.find(&(&1 == :idle))

t0 = System.monotonic_time()
{:ok, []} = DNC.request(cec, command, blocks)
elapsed_s = System.convert_time_unit(System.monotonic_time() - t0, :native, :microsecond) / 1.0e6

# the simulator files it once the EOT is in
Stream.repeatedly(fn ->
  Process.sleep(5)
  GE2000.program(sim, "004711.PRO")
end)
|> Enum.find(& &1)

exact? = GE2000.program(sim, "004711.PRO") == text

cpu =
  case File.read("/proc/cpuinfo") do
    {:ok, info} ->
      Regex.run(~r/model name\s*:\s*(.*)/, info, capture: :all_but_first)
      |> List.wrap()
      |> List.first()

    _ ->
      nil
  end

deviation = (elapsed_s - limit_s) / limit_s * 100
counters = DNC.info(cec).counters

IO.puts("""
DNC Level 2 download benchmark
  machine        #{cpu || "unknown CPU"}, #{System.schedulers_online()} schedulers, #{:erlang.system_info(:system_architecture)}
  runtime        Erlang/OTP #{System.otp_release()}, Elixir #{System.version()}
  line           #{baud} Bd, #{char_bits} bits a character (8N1), paced by the simulator
  program        #{size} bytes, #{length(lines)} lines, #{length(blocks)} text blocks of at most #{block} bytes (LRC)
  on the line    #{master} characters CEC → GE, #{slave} GE → CEC, #{chars} in all
  limit          #{Float.round(limit_s, 3)} s   (stop-and-wait, zero turnaround: #{Float.round(size / limit_s, 1)} program bytes/s)
  measured       #{Float.round(elapsed_s, 3)} s   (#{Float.round(size / elapsed_s, 1)} program bytes/s)
  deviation      #{Float.round(deviation, 3)} %   (target within 1 %: #{if abs(deviation) <= 1.0, do: "MET", else: "MISSED"})
  retries        #{counters.retransmissions} retransmissions, #{counters.enqs_sent - 1} ENQ polls
  byte-exact     #{exact?}
""")
