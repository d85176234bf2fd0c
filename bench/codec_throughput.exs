# Throughput of the pure codecs, one process on one scheduler: WC command strings parsed
# (line framing + BCC + parse), WC replies encoded, DDCMP data messages and DNC text blocks
# encoded and decoded, CRC-16 over a large binary.
#
#     mix run bench/codec_throughput.exs [--ms 1000]
#
# Each figure is the best of five loops of --ms/5 milliseconds (after a short warm-up each): on a
# shared machine other work only slows a loop down.
# The seed's lines are slow (9600 Bd is 960 characters a second), so every figure here is
# compared with the line it serves: how many such lines one core could keep busy.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench
alias Vws.Codecs.WC.{CommandString, LineDecoder, Reply}
alias Vws.Links.DDCMP.Frame, as: DDCMP
alias Vws.Links.DNC.Frame, as: DNC

{opts, _, _} = OptionParser.parse(System.argv(), strict: [ms: :integer])
ms = Keyword.get(opts, :ms, 1_000)

# --- WC: seed Table 1, step 1 (a robot move and a gripper command in one string) ---------------
wc_line = "*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*241"
wc_bytes = wc_line <> "\r\n"
{:ok, %CommandString{commands: [_, _]}} = CommandString.decode(wc_line)
status_line = "*0055*S0039ROBOT_CMD*032"
{:ok, _} = CommandString.decode(status_line)
decoder = LineDecoder.new(max_line: 1024)

wc_parse = fn ->
  {[line], _} = LineDecoder.feed(decoder, wc_bytes)
  {:ok, _} = CommandString.decode(line)
end

wc_status = fn -> {:ok, _} = CommandString.decode(status_line) end
wc_reply = fn -> IO.iodata_to_binary(Reply.encode({:status, 39, "0009DONE"})) end

# --- DDCMP: a VAL II message of 64 data bytes, encoded then decoded -----------------------------
payload = :binary.copy(<<"VAL II DATA ">>, 6) |> binary_part(0, 64)
ddcmp_frame = DDCMP.data(17, 16, payload)
ddcmp_decoder = DDCMP.new()

ddcmp_round = fn ->
  bytes = IO.iodata_to_binary(DDCMP.encode(ddcmp_frame))
  {[%DDCMP.Data{}], _} = DDCMP.feed(ddcmp_decoder, bytes)
end

ddcmp_wire = byte_size(IO.iodata_to_binary(DDCMP.encode(ddcmp_frame)))

# --- DNC: a 256-byte part-program block, LRC and CRC, encoded then decoded ----------------------
text = :binary.copy("N10 G01 X12.5 Y-3.25 F300\n", 10) |> binary_part(0, 256)

dnc_round = fn check ->
  frame = %DNC.Text{text: text}
  decoder = DNC.new(check: check, max_text: 256)

  fn ->
    bytes = IO.iodata_to_binary(DNC.encode(frame, check: check, max_text: 256))
    {[%DNC.Text{}], _} = DNC.feed(decoder, bytes)
  end
end

dnc_lrc = dnc_round.(:lrc)
dnc_crc = dnc_round.(:crc)
dnc_wire = byte_size(IO.iodata_to_binary(DNC.encode(%DNC.Text{text: text}, max_text: 256)))

# --- CRC-16 over 1 MiB --------------------------------------------------------------------------
mib = :crypto.strong_rand_bytes(1_048_576)
crc = fn -> Vws.Codecs.CRC16.compute(mib) end

measure = fn fun -> Bench.best_of(5, ms, fun) end
rate = fn {calls, us} -> calls * 1_000_000 / us end
per = fn {calls, us} -> us / calls end

r_wc = measure.(wc_parse)
r_status = measure.(wc_status)
r_reply = measure.(wc_reply)
r_ddcmp = measure.(ddcmp_round)
r_lrc = measure.(dnc_lrc)
r_crc_block = measure.(dnc_crc)
r_crc = Bench.best_of(5, ms, crc)

crc_mb_s = elem(r_crc, 0) * 1.0 / (elem(r_crc, 1) / 1_000_000)

line = fn name, r, unit, extra ->
  String.pad_trailing("  #{name}", 36) <>
    String.pad_leading(Bench.thousands(rate.(r)), 12) <>
    " #{unit}   #{Bench.us(per.(r))} µs each#{extra}"
end

# characters a second on a line at `baud`, 10 bits a character
cps = fn baud -> baud / 10 end

IO.puts(
  Enum.join(
    [
      "Codec throughput (one process; each figure the best of 5 runs of #{div(ms, 5)} ms)"
      | Bench.machine()
    ] ++
      [
        line.(
          "WC string parsed (framing+BCC)",
          r_wc,
          "strings/s",
          " (#{byte_size(wc_bytes)} bytes: seed Table 1 step 1)"
        ),
        line.("WC status string parsed", r_status, "strings/s", ""),
        line.("WC status reply encoded", r_reply, "replies/s", ""),
        line.(
          "DDCMP data message enc+dec",
          r_ddcmp,
          "frames/s",
          " (64 data bytes, #{ddcmp_wire} on the wire, 2 CRCs)"
        ),
        line.(
          "DNC text block enc+dec, LRC",
          r_lrc,
          "blocks/s",
          " (256 text bytes, #{dnc_wire} on the wire)"
        ),
        line.("DNC text block enc+dec, CRC-16", r_crc_block, "blocks/s", ""),
        String.pad_trailing("  CRC-16/ARC", 36) <>
          String.pad_leading(:erlang.float_to_binary(crc_mb_s, decimals: 1), 12) <>
          " MiB/s   (1 MiB binary, table-driven, pure Elixir)",
        String.pad_trailing("  one line's worth", 36) <>
          "a 9600 Bd WC line carries at most #{round(cps.(9600) / byte_size(wc_bytes))} such strings/s, a 9600 Bd",
        String.pad_trailing("", 36) <>
          "DDCMP line #{round(cps.(9600) / ddcmp_wire)} such messages/s, a 4800 Bd DNC line #{Float.round(cps.(4800) / dnc_wire, 1)} blocks/s",
        String.pad_trailing("  headroom of one core", 36) <>
          "WC #{Bench.thousands(rate.(r_wc) / (cps.(9600) / byte_size(wc_bytes)))}×, DDCMP #{Bench.thousands(rate.(r_ddcmp) / (cps.(9600) / ddcmp_wire))}×, DNC #{Bench.thousands(rate.(r_lrc) / (cps.(4800) / dnc_wire))}× its line rate"
      ],
    "\n"
  )
)
