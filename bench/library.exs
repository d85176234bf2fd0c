# The program library (issue 18) with 10,000 programs: store, list, compare — the operations
# a person waits on at iex, the dashboard and `mix vws.library`. Each is timed on a library of
# that size on a real directory (the default temporary directory: give --dir to measure another
# file system). The compare is timed two ways: from the machine's directory as recorded (what
# the dashboard and `mix vws.library compare` do) and live against a simulated GE-2000 holding
# the same 10,000 programs (its directory read over the DNC link, unpaced TCP — at 4800 Bd the
# line alone takes ~48 s per 10,000 directory lines, ~23 bytes each).
#
#     mix run bench/library.exs [--programs 10000] [--dir DIR] [--no-live]
#
# Run by hand.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :warning)

alias Vws.CEC.Library

{opts, _, _} =
  OptionParser.parse(System.argv(), strict: [programs: :integer, dir: :string, live: :boolean])

n = Keyword.get(opts, :programs, 10_000)
root = Keyword.get(opts, :dir, System.tmp_dir!())
dir = Path.join(root, "vws-bench-library-#{:os.getpid()}")
lib = {:dir, dir}

text = fn i, v ->
  "%\nO#{i}\nN10 G90 G00 X0 Y0\nN20 G01 X#{rem(i * 37, 1000)}.#{v} Y-12.25 F300\nN30 M30\n%\n"
end

ms = fn us -> :erlang.float_to_binary(us / 1000, decimals: 2) <> " ms" end

# wall time (µs) and the VM's CPU time (ms, every scheduler; nothing else runs meanwhile)
timed = fn fun ->
  {_, _} = :erlang.statistics(:runtime)
  {us, result} = :timer.tc(fun)
  {_, cpu_ms} = :erlang.statistics(:runtime)
  {us, cpu_ms, result}
end

cpu = fn list -> "CPU p50 #{Vws.Bench.pct(list, 0.5)} ms" end

IO.puts("Program library, #{n} programs, in #{dir}")
Enum.each(Vws.Bench.machine(), &IO.puts/1)

# filling it: every program one version (the time per store as the library grows)
{fill_us, store_us} =
  :timer.tc(fn ->
    for i <- 1..n do
      {us, {:ok, _}} = :timer.tc(fn -> Library.store(lib, i, text.(i, 1), source: "cli") end)
      us
    end
  end)

IO.puts(
  "  fill           #{n} stores in #{ms.(fill_us)} (#{Vws.Bench.summary(store_us, ms)} each, fsync included)"
)

# one more version of programs already there, into the full library
store_more =
  for i <- Enum.take_random(1..n, 200) do
    {us, {:ok, _}} = :timer.tc(fn -> Library.store(lib, i, text.(i, 2), source: "wc") end)
    us
  end

IO.puts(
  "  store          200 new versions into the full library: #{Vws.Bench.summary(store_more, ms)}"
)

{list, list_cpu} =
  Enum.unzip(
    for _ <- 1..10 do
      {us, cpu_ms, {:ok, programs}} = timed.(fn -> Library.list(lib) end)
      ^n = length(programs)
      {us, cpu_ms}
    end
  )

IO.puts(
  "  list           every program with its versions (#{n}): #{Vws.Bench.summary(list, ms)}; #{cpu.(list_cpu)}"
)

versions =
  for i <- Enum.take_random(1..n, 200) do
    {us, {:ok, _, _}} = :timer.tc(fn -> Library.read(lib, i, 1) end)
    us
  end

IO.puts(
  "  read           one version by number (CRC checked): #{Vws.Bench.summary(versions, ms)}"
)

# the machine holds every program's version 1 (so some are the same, 200 not the latest)
files = for i <- 1..n, do: {String.pad_leading("#{i}", 6, "0") <> ".PRO", text.(i, 1)}
entries = Map.new(files, fn {name, t} -> {name, Vws.Links.DNC.Report.entry(name, t)} end)
{rec_us, :ok} = :timer.tc(fn -> Library.record_machine(lib, entries) end)
IO.puts("  record         the machine's directory of #{n} entries: #{ms.(rec_us)}")

{compare, compare_cpu} =
  Enum.unzip(
    for _ <- 1..10 do
      {us, cpu_ms, {:ok, c}} = timed.(fn -> Library.compare(lib) end)
      ^n = length(c.programs)
      {us, cpu_ms}
    end
  )

IO.puts(
  "  compare        all #{n} from the recorded directory: " <>
    "#{Vws.Bench.summary(compare, ms)}; #{cpu.(compare_cpu)}"
)

{:ok, c} = Library.compare(lib)

counts =
  Enum.frequencies_by(c.programs, fn p ->
    case p.on_machine do
      {:same, v} -> "same as v#{v}"
      other -> other
    end
  end)

IO.puts("                 (#{inspect(counts)})")

if Keyword.get(opts, :live, true) do
  {:ok, sim} = Vws.Sim.GE2000.start_link(programs: Map.new(files))
  id = "BENCH-LIB"

  {:ok, _} =
    Vws.CEC.Workstation.start(
      id: id,
      wc: nil,
      devices: [ge2000: [endpoint: Vws.Sim.GE2000.endpoint(sim), status_interval: nil]],
      library: dir
    )

  link = Vws.CEC.Workstation.whereis(id, :ge2000)

  Stream.repeatedly(fn -> Process.sleep(20) && Vws.Links.DNC.info(link).state end)
  |> Enum.find(&(&1 == :idle))

  live =
    for _ <- 1..3 do
      {us, {:ok, c}} = :timer.tc(fn -> Vws.Partitions.Monarch.compare(id) end)
      ^n = length(c.programs)
      us
    end

  IO.puts(
    "  compare live   directory read from the simulated GE-2000 (unpaced) + compare: #{Vws.Bench.summary(live, ms)}"
  )

  {us, {:ok, c}} =
    :timer.tc(fn -> Vws.Partitions.Monarch.compare(id, read_back: ["000001.PRO"]) end)

  :same = hd(c.programs).read_back
  IO.puts("  + read-back    of one program: #{ms.(us)}")
  Vws.CEC.Workstation.stop(id)
end

{dash_us, dash_cpu, _} = timed.(fn -> Vws.Ops.Web.State.library(lib) end)

IO.puts(
  "  dashboard      the library section of /api/state: #{ms.(dash_us)} (CPU #{dash_cpu} ms); " <>
    "read again after 10x that (Vws.Ops.Web.State.library/2)"
)

File.rm_rf!(dir)
