# Safety soak: the stateful safety test (test/vws/safety_statem_test.exs) for 10 000 random
# sequences instead of 300. Each sequence runs on a fresh simulated floor — plant, DAQ #1,
# GE-2000, VAL II, material handling — with a workstation wired to it: random WC commands for
# every partition, tray moves and injected faults (Vws.Test.SafetyModel). After every step and
# at the end the plant's collision oracle must have recorded nothing, and every command must
# have ended DONE or ERROR with a reason.
#
#     MIX_ENV=test mix run bench/safety_soak.exs [--sequences 10000] [--size 10]
#
# (MIX_ENV=test: the model lives in test/support.) It takes about 15–25 minutes on two cores.
# On a failure PropEr shrinks the sequence and the shortest one found is printed. At the end it
# prints what the sequences exercised: how each command ended, how often.

Logger.configure(level: :error)

alias Vws.Test.SafetyModel

{opts, _, _} = OptionParser.parse(System.argv(), strict: [sequences: :integer, size: :integer])
sequences = Keyword.get(opts, :sequences, 10_000)
size = Keyword.get(opts, :size, 10)

Process.put(:safety_stats, %{})
counter = :counters.new(2, [])
started = System.monotonic_time(:millisecond)

property =
  :proper.forall(SafetyModel.commands(size), fn cmds ->
    :counters.add(counter, 1, 1)
    :counters.add(counter, 2, length(cmds))
    n = :counters.get(counter, 1)

    if rem(n, 500) == 0 do
      s = (System.monotonic_time(:millisecond) - started) / 1000
      IO.puts("#{n} sequences, #{Float.round(s, 1)} s")
    end

    case SafetyModel.run(cmds) do
      :ok ->
        true

      {:failed, report} ->
        IO.puts("FAILED:\n" <> inspect(report, pretty: true, limit: :infinity))
        false
    end
  end)

result = :proper.quickcheck(property, [:quiet, {:numtests, sequences}, :long_result])
elapsed = (System.monotonic_time(:millisecond) - started) / 1000
runs = :counters.get(counter, 1)

IO.puts("""

== Safety soak ==
result:     #{if result == true, do: "PASSED", else: "FAILED"}
sequences:  #{runs} (#{:counters.get(counter, 2)} steps; size #{size})
elapsed:    #{Float.round(elapsed, 1)} s (#{Float.round(elapsed * 1000 / max(runs, 1), 1)} ms a sequence)
""")

if result != true do
  IO.puts("shortest failing sequence:\n" <> inspect(:proper.counterexample(), pretty: true))
end

IO.puts("how the commands ended (count, partition, command, outcome):")

for {{partition, text, outcome}, n} <- Enum.sort(Process.get(:safety_stats)) do
  outcome = if outcome == :done, do: "DONE", else: "ERROR " <> elem(outcome, 1)
  IO.puts("#{String.pad_leading(to_string(n), 7)}  #{partition} #{text}: #{outcome}")
end

if result != true, do: System.halt(1)
