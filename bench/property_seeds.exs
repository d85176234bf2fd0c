# Every property module of the suite on many seeds: the suite must pass on any seed (issue 24).
#
#     mix run --no-start bench/property_seeds.exs [--seeds 100] [--from 1] [--only test/a_test.exs,…]
#
# ExUnit seeds each test process's :rand from the run's seed, and PropEr draws its cases from
# that state, so `mix test FILE --seed S` replays exactly the cases of seed S. For each seed this
# runs one `mix test` (MIX_ENV=test, acceptance tests excluded) over every test file that uses
# PropEr (`Vws.PropCase`, `:proper…`), and reports every failing test with its seed and the
# command that replays it. Exit status 1 when anything failed. Run by hand: 100 seeds take about
# an hour on 2 cores.

{opts, _, _} =
  OptionParser.parse(System.argv(), strict: [seeds: :integer, from: :integer, only: :string])

seeds = Keyword.get(opts, :seeds, 100)
from = Keyword.get(opts, :from, 1)

files =
  case Keyword.get(opts, :only) do
    nil ->
      Path.wildcard("test/**/*_test.exs")
      |> Enum.reject(&String.starts_with?(&1, "test/acceptance/"))
      |> Enum.filter(&(File.read!(&1) =~ ~r/Vws\.PropCase|:proper(_statem|_types)?\./))
      |> Enum.sort()

    list ->
      String.split(list, ",", trim: true)
  end

Code.require_file("support.exs", __DIR__)

IO.puts("""
property seeds: #{length(files)} files, seeds #{from}..#{from + seeds - 1}
#{Enum.join(Vws.Bench.machine(), "\n")}
""")

# "  1) test name (Module)" or "  1) property name (Module)": the failures of one run
failures = fn output ->
  Regex.scan(~r/^\s+\d+\) (?:test|doctest|property) (.+) \(([\w.]+)\)\s*$/m, output)
  |> Enum.map(fn [_, name, module] -> {module, name} end)
end

file_of = fn module, output ->
  case Regex.run(~r/\(#{Regex.escape(module)}\)\s*\n\s+(test\/\S+_test\.exs):\d+/, output) do
    [_, file] -> file
    nil -> nil
  end
end

started = System.monotonic_time(:millisecond)
logs = Path.join(System.tmp_dir!(), "vws-property-seeds-#{System.os_time(:second)}")

results =
  for seed <- from..(from + seeds - 1) do
    t0 = System.monotonic_time(:millisecond)

    {output, status} =
      System.cmd("mix", ["test", "--seed", "#{seed}", "--exclude", "acceptance" | files],
        env: [{"MIX_ENV", "test"}],
        stderr_to_stdout: true
      )

    failed = failures.(output)
    ms = System.monotonic_time(:millisecond) - t0

    summary =
      case Regex.run(~r/^.*\d+ tests?, \d+ failures?.*$/m, output) do
        [line] -> line
        nil -> "no summary (exit #{status})"
      end

    IO.puts("seed #{seed}: #{summary} (#{Float.round(ms / 1000, 1)} s)")

    for {module, name} <- failed do
      IO.puts("  FAILED #{module}: #{name}")
    end

    # a failed run's whole output, to tell a wrong answer from a run starved of time
    if failed != [] or status != 0 do
      File.mkdir_p!(logs)
      path = Path.join(logs, "seed-#{seed}.log")
      File.write!(path, output)
      IO.puts("  output: #{path}")
    end

    # a run that failed without naming a test (a crash, a timeout of the whole run) counts too
    failed = if failed == [] and status != 0, do: [{"(the run itself)", summary}], else: failed

    {seed, Enum.map(failed, fn {m, n} -> {m, n, file_of.(m, output)} end)}
  end

all = for {seed, failed} <- results, {m, n, f} <- failed, do: {m, n, f, seed}
minutes = Float.round((System.monotonic_time(:millisecond) - started) / 60_000, 1)

IO.puts("\n== #{seeds} seeds in #{minutes} min: #{length(all)} failures ==")

all
|> Enum.group_by(fn {m, n, f, _} -> {m, n, f} end, fn {_, _, _, seed} -> seed end)
|> Enum.sort()
|> Enum.each(fn {{module, name, file}, seeds_failed} ->
  IO.puts("#{module}: #{name}")

  IO.puts(
    "  failed on #{length(seeds_failed)} of #{seeds} seeds: #{Enum.join(seeds_failed, ", ")}"
  )

  if file, do: IO.puts("  replay: mix test #{file} --seed #{hd(seeds_failed)}")
end)

if all != [], do: System.halt(1)
