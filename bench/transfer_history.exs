# The transfer history (issue 27): what one record costs to append (written and fsync'd before
# it counts), how many records a 1 MiB file holds, and what reading the newest records costs
# when the current file is full — what the dashboard does at every state build and `mix
# vws.library history --limit` does. On a real directory (the default temporary directory:
# give --dir to measure another file system).
#
#     mix run bench/transfer_history.exs [--appends 200] [--dir DIR]
#
# Run by hand.

alias Vws.CEC.Journal.Log
alias Vws.CEC.Library.History

{opts, _, _} = OptionParser.parse(System.argv(), strict: [appends: :integer, dir: :string])
appends = Keyword.get(opts, :appends, 200)
base = Keyword.get(opts, :dir, System.tmp_dir!())
dir = Path.join(base, "vws-history-bench-#{System.unique_integer([:positive])}")

record = fn i ->
  History.new(
    program: "004711.PRO",
    version: 12,
    digest: "9f86d081884c7d65",
    command: "DOWNLOAD_GE(004711.PRO/12)",
    operation: "part program",
    direction: "to machine",
    bytes: 150_000 + i,
    blocks: 586,
    duration_ms: 312_500,
    chars_per_s: 480,
    result: "DONE",
    retries: 2,
    requester: "WC string 0042 M0007"
  )
end

{us, _} = :timer.tc(fn -> for i <- 1..appends, do: :ok = History.append(dir, record.(i)) end)

IO.puts(
  "append, fsync'd: #{Float.round(us / appends / 1000, 2)} ms a record (#{appends} records)"
)

frame = byte_size(Log.record(record.(1)))
per_file = div(Keyword.fetch!(History.defaults(), :max_bytes), frame)
IO.puts("a record: #{frame} bytes framed; a 1 MiB file holds #{per_file}")

full = IO.iodata_to_binary([for(i <- 1..per_file, do: Log.record(record.(i))), Log.end_mark()])
File.write!(Path.join(dir, "transfers.log"), full)

for n <- [10, per_file] do
  {us, %{records: rs}} = :timer.tc(fn -> History.read(dir, n) end)

  IO.puts(
    "read the newest #{n} (a full file, #{length(rs)} records parsed): #{Float.round(us / 1000, 1)} ms"
  )
end

File.rm_rf!(dir)
