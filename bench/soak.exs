# The soak of issue 8: the shipped machining cycle run N times on the simulated floor with a
# bit-error rate on every link at once — the WC's, the VAL II's (DDCMP), the GE-2000's (DNC),
# DAQ #1's and the hydraulic controller's (HPIB) and the hydraulic controller's own to DAQ #2 —
# each cycle audited by Vws.Ops.Soak: completed, every retry counted from telemetry, commands
# lost (numbered by the WC, never ended in the CEC) and duplicated (started or ended twice in the
# CEC, or equipment that did more than the clean reference cycle), and silent differences (issue
# 15: the program's bytes in the CEC, the GE-2000 and back at the WC, and every relay, against
# what was sent and the clean cycle: what ended DONE but is not so).
#
#     mix run bench/soak.exs [--cycles 100] [--ber 1.0e-4] [--seed 1] [--time-scale 20]
#
# Prints a line per cycle, then one block of figures. After a stopped cycle the floor is
# recovered as an operator would (priv/sims/recover.vws, the blank back in tray #1), so that one
# stop does not stop every cycle after it. Exits 1 if a cycle did not complete, a command was
# lost or duplicated, or a silent difference was found.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [cycles: :integer, ber: :float, seed: :integer, time_scale: :float]
  )

cycles = Keyword.get(opts, :cycles, 100)
ber = Keyword.get(opts, :ber, 1.0e-4)
seed = Keyword.get(opts, :seed, 1)
time_scale = Keyword.get(opts, :time_scale, 20.0)
machine = Vws.Bench.machine()

report =
  Vws.Ops.Soak.run(
    cycles: cycles,
    ber: ber,
    seed: seed,
    time_scale: time_scale,
    on_cycle: fn n, s ->
      outcome = if s.result == :completed, do: "completed", else: "STOPPED: #{s.stopped.reason}"
      IO.puts("  cycle #{n}/#{cycles}: #{outcome} in #{s.elapsed_ms} ms")
    end
  )

r = report.retries

# after a stopped cycle the floor is recovered as an operator would (Vws.Ops.Soak)
recovered =
  case {report.recovered, report.unrecovered} do
    {[], nil} ->
      "none needed"

    {ns, nil} ->
      "after cycles #{Enum.join(ns, ", ")} (the recovery script, the blank back in tray #1)"

    {ns, {n, why}} ->
      done = if ns == [], do: "", else: "after cycles #{Enum.join(ns, ", ")}; "
      done <> "not after cycle #{n}: #{why} — the soak ended there"
  end

flipped = report.bits_flipped

IO.puts("""

== bench/soak.exs: the machining cycle under a bit-error rate on every link at once ==
#{Enum.join(machine, "\n")}
  faults         BER #{ber} on #{map_size(flipped)} links, seed #{seed}, time scale ×#{time_scale}
  bits flipped   #{Enum.map_join(Enum.sort(flipped), ", ", fn {l, n} -> "#{l} #{n}" end)}
  cycles         #{report.completed} of #{report.cycles} completed in #{Float.round(report.elapsed_ms / 1000, 1)} s#{if report.stopped == [], do: "", else: " — stopped: " <> inspect(report.stopped)}
  recovered      #{recovered}
  commands       #{report.commands} numbered by the WC: lost #{report.lost}, duplicated #{report.duplicated}#{if report.lost_commands == [], do: "", else: "\n                 lost: " <> inspect(report.lost_commands)}#{if report.duplicates == [], do: "", else: "\n                 duplicated: " <> inspect(report.duplicates)}
  silent         #{report.silent_differences} silent differences (program bytes at the CEC, the GE-2000 and the WC; relays)#{if report.silent == [], do: "", else: ": " <> inspect(report.silent)}
  retries        #{Enum.sum(Map.values(r))} in all: WC strings/lines sent again #{r.wc_resends}, transfers made again #{r.transfers_made_again},
                 retransmissions recognised by SUN_COMM #{r.sun_comm_retransmissions}, DDCMP retransmissions #{r.ddcmp_retransmissions},
                 DNC retries #{r.dnc_retries}, DNC requests made again #{r.dnc_requests_made_again}, HPIB requests tried again #{r.hpib_retries}, relays set again #{r.relays_set_again}
""")

if report.completed != report.cycles or report.lost != 0 or report.duplicated != 0 or
     report.silent_differences != 0,
   do: System.halt(1)
