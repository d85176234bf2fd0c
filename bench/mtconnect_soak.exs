# The MTConnect soak of issue 19: the shipped machining cycle run again and again on the
# simulated floor (time scale ×20 by default) while a client pages through /sample over real
# HTTP — each page from the nextSequence of the page before — and a second client streams
# /sample?interval=0&heartbeat=1000. Every observation's sequence number is checked: a page (or a
# part) must hold exactly the sequence numbers from its `from` to its nextSequence - 1, so a
# sequence number missing is a gap and one seen twice a duplicate.
#
#     mix run bench/mtconnect_soak.exs [--duration 3600] [--time-scale 20] [--count 100] [--pause-ms 200]
#
# Prints a line a minute, then one block of figures. Exits 1 on any gap, duplicate or error
# document. A cycle that did not complete (the floor's own trouble, e.g. DAQ #1 not answering on
# an overloaded machine) is reported, not counted against the agent: its commands and errors are
# observations like any other.

Code.require_file("support.exs", __DIR__)
Code.require_file("../test/support/mtc_client.ex", __DIR__)
Logger.configure(level: :error)

alias Vws.Test.MTCClient
alias Vws.Peers.WC.{Client, Runner, Script}

{opts, _, _} =
  OptionParser.parse(System.argv(),
    strict: [duration: :integer, time_scale: :float, count: :integer, pause_ms: :integer]
  )

duration_s = Keyword.get(opts, :duration, 3600)
time_scale = Keyword.get(opts, :time_scale, 20.0)
count = Keyword.get(opts, :count, 100)
pause_ms = Keyword.get(opts, :pause_ms, 200)
ws = "VWS-SOAK"

{:ok, floor} = Vws.Ops.Demo.start_shop_floor(id: ws, wc: "loopback:#{ws}", time_scale: time_scale)
{:ok, web} = Vws.Ops.Web.start_link(port: 0)
"http://127.0.0.1:" <> rest = Vws.Ops.Web.url(web)
port = rest |> String.trim_trailing("/") |> String.to_integer()
{:ok, script} = Script.parse_file(Vws.Ops.Demo.default_script())
{:ok, client} = Client.connect(floor.wc)

started = System.monotonic_time(:millisecond)
deadline = started + duration_s * 1000
bench = self()

# the WC: cycle after cycle until the deadline
cycler =
  spawn_link(fn ->
    Stream.iterate(1, &(&1 + 1))
    |> Enum.reduce_while(:ok, fn n, _ ->
      if System.monotonic_time(:millisecond) >= deadline do
        {:halt, :ok}
      else
        s = Runner.run(client, script, poll_interval: 20)
        send(bench, {:cycle, n, s.result, Map.get(s, :stopped)})
        {:cont, :ok}
      end
    end)

    send(bench, :cycles_done)
  end)

_ = cycler

# the streaming client
{:ok, _} = :application.ensure_all_started(:inets)
{_, _, current} = MTCClient.get(port, "/current")
start_seq = MTCClient.header(current, "nextSequence")

{sref, spid, _head} =
  MTCClient.stream(port, "/sample?interval=0&heartbeat=1000&count=#{count}&from=#{start_seq}")

check = fn from, doc ->
  seqs = doc |> MTCClient.observations() |> Enum.map(&elem(&1, 2)) |> Enum.sort()
  next = MTCClient.header(doc, "nextSequence")
  expected = Enum.to_list(from..(next - 1)//1)
  gaps = length(expected -- seqs)
  dups = length(seqs) - length(Enum.uniq(seqs)) + length((seqs -- expected) -- expected -- seqs)
  {next, length(seqs), gaps, dups}
end

# the paging client, a process of its own: a page every `pause_ms`, each from the nextSequence
# of the page before; it reports each page to the bench
spawn_link(fn ->
  page = fn page, from ->
    Process.sleep(pause_ms)
    {status, _type, doc} = MTCClient.get(port, "/sample?from=#{from}&count=#{count}")

    if status == 200 do
      {next, n, gaps, dups} = check.(from, doc)
      send(bench, {:page, n, gaps, dups})
      page.(page, next)
    else
      send(bench, {:page_error, doc})
      page.(page, from)
    end
  end

  page.(page, start_seq)
end)

collect = fn collect, acc ->
  receive do
    {:cycle, n, result, stopped} ->
      acc = %{
        acc
        | cycles: acc.cycles + 1,
          failed: acc.failed + if(result == :completed, do: 0, else: 1)
      }

      if result != :completed,
        do: IO.puts("  cycle #{n}: #{result} #{inspect(stopped, limit: 10)}")

      collect.(collect, acc)

    :cycles_done ->
      acc

    {:page, n, gaps, dups} ->
      acc = %{
        acc
        | pages: acc.pages + 1,
          obs: acc.obs + n,
          gaps: acc.gaps + gaps,
          dups: acc.dups + dups
      }

      now = System.monotonic_time(:millisecond)

      acc =
        if now - acc.reported >= 60_000 do
          IO.puts(
            "  #{div(now - started, 60_000)} min: cycles #{acc.cycles} (#{acc.failed} stopped), pages #{acc.pages}, observations #{acc.obs}, gaps #{acc.gaps}, duplicates #{acc.dups}; stream parts #{acc.parts}, gaps #{acc.stream_gaps}, duplicates #{acc.stream_dups}"
          )

          %{acc | reported: now}
        else
          acc
        end

      collect.(collect, acc)

    {:page_error, doc} ->
      IO.puts("  error document: #{doc}")
      collect.(collect, %{acc | errors: acc.errors + 1})

    {:mtc_part, ^sref, doc} ->
      {next, n, gaps, dups} = check.(acc.stream_from, doc)

      collect.(collect, %{
        acc
        | stream_from: next,
          parts: acc.parts + 1,
          heartbeats: acc.heartbeats + if(n == 0, do: 1, else: 0),
          stream_obs: acc.stream_obs + n,
          stream_gaps: acc.stream_gaps + gaps,
          stream_dups: acc.stream_dups + dups
      })
  end
end

acc0 = %{
  cycles: 0,
  failed: 0,
  pages: 0,
  obs: 0,
  gaps: 0,
  dups: 0,
  errors: 0,
  from: start_seq,
  stream_from: start_seq,
  parts: 0,
  heartbeats: 0,
  stream_obs: 0,
  stream_gaps: 0,
  stream_dups: 0,
  reported: started
}

acc = collect.(collect, acc0)

# the paging client catches up with what the buffer holds now: its pages until one is empty
catch_up = fn catch_up, acc ->
  receive do
    {:page, 0, gaps, dups} ->
      %{acc | pages: acc.pages + 1, gaps: acc.gaps + gaps, dups: acc.dups + dups}

    {:page, n, gaps, dups} ->
      catch_up.(catch_up, %{
        acc
        | pages: acc.pages + 1,
          obs: acc.obs + n,
          gaps: acc.gaps + gaps,
          dups: acc.dups + dups
      })

    {:page_error, _doc} ->
      catch_up.(catch_up, %{acc | errors: acc.errors + 1})

    _other ->
      catch_up.(catch_up, acc)
  after
    60_000 -> acc
  end
end

acc = catch_up.(catch_up, acc)
MTCClient.stop(spid)
{_, _, current} = MTCClient.get(port, "/current")
elapsed = (System.monotonic_time(:millisecond) - started) / 1000

IO.puts("""

== bench/mtconnect_soak.exs: a client paging /sample and one streaming it through machining cycles ==
#{Enum.join(Vws.Bench.machine(), "\n")}
  run            #{Float.round(elapsed, 1)} s at time scale ×#{time_scale} (#{Float.round(elapsed * time_scale / 3600, 2)} simulated hours)
  cycles         #{acc.cycles} run, #{acc.failed} did not complete (the floor's trouble: reported above)
  paging         #{acc.pages} pages of count=#{count}: #{acc.obs} observations from #{start_seq}, gaps #{acc.gaps}, duplicates #{acc.dups}, error documents #{acc.errors}
  streaming      #{acc.parts} parts (#{acc.heartbeats} heartbeats): #{acc.stream_obs} observations, gaps #{acc.stream_gaps}, duplicates #{acc.stream_dups}
  buffer         firstSequence #{MTCClient.header(current, "firstSequence")}, nextSequence #{MTCClient.header(current, "nextSequence")}, bufferSize #{MTCClient.header(current, "bufferSize")}
  rate           #{Float.round(acc.obs / max(elapsed, 1) * 60, 1)} observations a minute (at ×#{time_scale})
""")

if acc.gaps + acc.dups + acc.errors + acc.stream_gaps + acc.stream_dups > 0,
  do: System.halt(1)
