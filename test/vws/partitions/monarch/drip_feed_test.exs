# Two modules (each its own floor), so that the feed into a machine slower than the paced line
# (about 25 s of the machine's own time) runs beside the others: one module of all was 52 s, the
# longest of the suite's modules.
for part <- [1, 2] do
  defmodule Module.concat(Vws.Partitions.Monarch.DripFeedTest, "Part#{part}") do
    # Drip feed (DRIP_FEED, the E operation), auto-receive and transfer progress, end to end:
    # the WC (a raw WC peer) → SUN_COMM → MONARCH → DNC link → simulated GE-2000.
    use ExUnit.Case, async: true

    alias Vws.Links.DNC
    alias Vws.CEC.{Mailbox, Workstation}
    alias Vws.Links.DNC.Program
    alias Vws.Sim.GE2000
    alias Vws.Test.WCPeer
    import Vws.Test.Eventually

    @link_opts [reply_timeout: 300, wack_delay: 50, backoff_min: 10, backoff_max: 50]
    @memory 2_048

    setup context do
      # a test with no fault on the line may give the link a longer reply timeout (tag :link): a
      # loaded machine answered a block of the paced feed later than 3 × 300 ms
      link_opts = Keyword.merge(@link_opts, Map.get(context, :link, []))

      sim_opts =
        [
          cycle_time: 60_000,
          link: link_opts,
          memory: @memory,
          feed_rate: Map.get(context, :feed_rate, 20_000),
          tick: 5,
          programs: %{"000100.PRO" => "%\nO100\nN10 G01 X1\nN20 M30\n%\n"}
        ] ++ if(baud = context[:baud], do: [pace: baud], else: [])

      sim = start_supervised!({GE2000, sim_opts})

      %{ws: ws, wc: wc} =
        Vws.Test.Workstation.start(
          devices: [ge2000: [endpoint: GE2000.endpoint(sim)] ++ link_opts],
          partitions: [monarch: [options: Map.get(context, :monarch, [])]],
          # (the auto-receive tests': programs from the machine go to the library)
          library: context[:tmp_dir]
        )

      link = Workstation.whereis(ws, :ge2000)
      assert eventually(fn -> DNC.info(link).state == :idle end)
      {:ok, peer} = WCPeer.connect(wc)
      %{ws: ws, peer: peer, sim: sim, link: link, monarch: Map.get(context, :monarch, [])}
    end

    defp seq, do: rem(System.unique_integer([:positive]), 10_000)

    defp send_monarch(peer, number, text) do
      s = seq()
      WCPeer.send_string(peer, s, [{"M", number, text}])
      assert Vws.Codecs.WC.Reply.decode(WCPeer.recv_line(peer)) == {:ok, {:ack, s}}
    end

    defp finished(peer, timeout \\ 60_000),
      do: WCPeer.await_status(peer, seq(), "MONARCH_CMD", &(not (&1 =~ "EXECUTING")), timeout)

    defp monarch(peer, number, text, timeout \\ 60_000) do
      send_monarch(peer, number, text)
      finished(peer, timeout)
    end

    # An NC program of at least `bytes` bytes of short blocks, O4711.
    defp program(bytes) do
      count = div(bytes, 18) + 1

      body = for i <- 1..count, do: "N#{i} G01 X#{rem(i * 37, 1000)}.#{rem(i, 10)} F300"

      ["%", "O4711"] ++ body ++ ["M30", "%"]
    end

    defp with_nc_file(ctx, bytes) do
      lines = program(bytes)
      :ok = Mailbox.put_nc_file(ctx.ws, lines)
      text = Program.to_text(lines)
      assert byte_size(text) > bytes
      text
    end

    defp assert_fed_exactly(sim, text) do
      assert eventually(fn -> GE2000.drip(sim).state == :done end, 30_000)
      drip = GE2000.drip(sim)
      # every block once, in order: the machine ran exactly the program's bytes
      assert drip.received == byte_size(text)
      assert drip.ran == byte_size(text)
      assert drip.crc == Vws.Codecs.CRC16.compute(text)
      assert drip.blocks == length(Vws.Links.DNC.Frame.split_text(text, 256))
      assert drip.max_fill <= @memory
      drip
    end

    if part == 2 do
      defp collect_progress(acc) do
        receive do
          {:vws_event, _ws, :dnc_progress, %{ended: ended} = p} when ended != false -> [p | acc]
          {:vws_event, _ws, :dnc_progress, p} -> collect_progress([p | acc])
        after
          10_000 -> acc
        end
      end

      @tag feed_rate: 1_500, link: [reply_timeout: 2_000]
      test "a machine slower than the line pauses the CEC with WACK; nothing skipped or repeated",
           ctx do
        text = with_nc_file(ctx, 4 * @memory)
        :ok = Vws.CEC.Events.subscribe(ctx.ws, :dnc_progress)
        assert monarch(ctx.peer, 1, "DRIP_FEED") == "0001DONE"
        assert_fed_exactly(ctx.sim, text)
        wacks = DNC.info(ctx.link).counters.wacks_received
        assert wacks > 0

        # the WACKs are pauses, counted as pauses (issue 25: they were counted as retries; a loaded
        # machine may still add ENQs, which are retries), and progress kept flowing through them
        [last | _] = progress = collect_progress([])
        assert last.ended == :ok
        assert last.pauses == wacks
        assert length(progress) > 10
      end

      for fault <- [:nak_once_per_block, :drop_replies, {:wack, 5}] do
        test "line faults during a drip feed (#{inspect(fault)}): the program runs exactly once",
             ctx do
          text = with_nc_file(ctx, 3 * @memory)
          :ok = GE2000.set_fault(ctx.sim, unquote(Macro.escape(fault)))
          assert monarch(ctx.peer, 1, "DRIP_FEED") == "0001DONE"
          assert_fed_exactly(ctx.sim, text)
        end
      end

      test "a drip feed the line broke off ends ERROR and is not made again: the machine stops",
           ctx do
        test_pid = self()
        handler = "drip-again-#{System.unique_integer([:positive])}"

        :ok =
          Vws.Telemetry.attach(
            handler,
            [:vws, :monarch, :request_again],
            fn _, _, md, _ ->
              if md.workstation == ctx.ws, do: send(test_pid, {:request_again, md.operation})
            end,
            nil
          )

        on_exit(fn -> Vws.Telemetry.detach(handler) end)
        with_nc_file(ctx, 6 * @memory)
        send_monarch(ctx.peer, 1, "DRIP_FEED")
        assert eventually(fn -> GE2000.drip(ctx.sim) != nil end)
        :ok = GE2000.set_fault(ctx.sim, :silent)
        assert finished(ctx.peer) =~ ~r/^0001ERROR DNC/
        refute_received {:request_again, :download_execute}
        :ok = GE2000.set_fault(ctx.sim, :none)
        assert eventually(fn -> GE2000.drip(ctx.sim).state == :broken end, 30_000)
      end

      # Issue 24 item 4 (docs/dnc-drip-feed.md "DONE means done"): an ENQ damaged into EOT looks
      # like the end of the transmission to the machine, which stops (no closing %). The rest of the
      # program reaches it as text without a command: with CRC blocks (MONARCH's default) it reads
      # them with the LRC of a command-less transmission, refuses them and the link ends ERROR; with
      # LRC blocks it takes them as unsolicited text and the link ends DONE — and the machine's
      # status report, read after every transmission, says it stopped.
      for check <- [:crc, :lrc] do
        @tag monarch: [check: check]
        test "an ENQ damaged into EOT mid-feed (#{check}): the machine stops and DRIP_FEED ends ERROR",
             ctx do
          with_nc_file(ctx, 3 * @memory)
          :ok = GE2000.set_fault(ctx.sim, {:enq_as_eot, 3})

          expected =
            if ctx.monarch[:check] == :lrc,
              do: ~r/^0001ERROR DRIP FEED OF 004711.PRO FAILED GE-2000 ALARM 7$/,
              else: ~r/^0001ERROR DNC /

          assert monarch(ctx.peer, 1, "DRIP_FEED") =~ expected
          assert GE2000.drip(ctx.sim).state == :broken
          assert GE2000.state(ctx.sim).alarm == 7
        end
      end

      test "transfer progress: telemetry, the :dnc_progress event and DNC.progress/1", ctx do
        text = with_nc_file(ctx, 4 * @memory)
        :ok = Vws.CEC.Events.subscribe(ctx.ws, :dnc_progress)
        send_monarch(ctx.peer, 1, "DRIP_FEED")
        assert eventually(fn -> DNC.progress(ctx.link) != nil end)
        # the dashboard's progress bar (this workstation's: building every one of a full suite's
        # took longer than the transfer lasted)
        assert eventually(fn ->
                 Enum.any?(Vws.Ops.Web.State.build(workstations: [ctx.ws]).workstations, fn w ->
                   Enum.any?(
                     Map.get(w, :transfers, []),
                     # which command and which program (the row had "number": null)
                     &(&1.kind == "DRIP_FEED" and &1.percent >= 0 and &1.number == "0001" and
                         &1.program == "004711.PRO")
                   )
                 end)
               end)

        assert finished(ctx.peer) == "0001DONE"

        events = collect_progress([])
        assert [%{ended: :ok} = last | running] = events
        assert last.program == "004711.PRO"
        assert last.operation == :download_execute
        assert last.direction == :out
        assert last.program_bytes == byte_size(text)
        assert last.total_program_bytes == byte_size(text)
        assert last.bytes == last.total_bytes
        assert last.blocks == last.total_blocks
        blocks = running |> Enum.reverse() |> Enum.map(& &1.blocks)
        assert blocks == Enum.sort(blocks)
        assert length(blocks) >= 2
      end

      describe "auto-receive" do
        @describetag :tmp_dir

        # the program 000100.PRO the machine sent: in the library, from the machine (never NC_UP)
        defp from_machine?(ws) do
          match?(
            {:ok, "%\nO100\nN10 G01 X1\nN20 M30\n%\n", %{source: "from the machine"}},
            Vws.CEC.Library.read(ws, "000100.PRO", 1)
          )
        end

        test "the operator sends a program from the machine: MONARCH keeps it in the library",
             ctx do
          assert GE2000.send_program(ctx.sim, "000100.PRO") == :ok
          assert eventually(fn -> from_machine?(ctx.ws) end)
          assert Mailbox.nc_up(ctx.ws) == []
        end

        test "during a WC command: the command is not disturbed, the program is kept", ctx do
          text = with_nc_file(ctx, 6 * @memory)
          send_monarch(ctx.peer, 1, "DRIP_FEED")
          assert eventually(fn -> GE2000.drip(ctx.sim) != nil end)
          sent = Task.async(fn -> GE2000.send_program(ctx.sim, "000100.PRO") end)
          assert finished(ctx.peer) == "0001DONE"
          assert Task.await(sent, 30_000) == :ok
          assert_fed_exactly(ctx.sim, text)

          assert eventually(fn -> from_machine?(ctx.ws) end)

          # and the line is MONARCH's again
          assert monarch(ctx.peer, 2, "STATUS") == "0002DONE"
        end
      end
    end

    if part == 1 do
      test "DRIP_FEED: a program 8 times the machine's memory is run while it arrives", ctx do
        text = with_nc_file(ctx, 8 * @memory)
        assert monarch(ctx.peer, 1, "DRIP_FEED") == "0001DONE"
        assert_fed_exactly(ctx.sim, text)
        # the machine did not store it: it ran it
        refute "004711.PRO" in GE2000.directory(ctx.sim)
      end

      # Issue 25: while the GE-2000 ran a drip-fed program, MONARCH said IDLE (the monitor's status
      # read waited for the line the feed held). From its first block until it ends, the WC's MONARCH
      # status says ACTIVE and the report names the program it runs.
      @tag feed_rate: 1_500
      test "MONARCH says ACTIVE, naming the program, from the first block until it has run",
           ctx do
        _text = with_nc_file(ctx, 3 * @memory)
        :ok = Vws.CEC.Events.subscribe(ctx.ws, :dnc_progress)
        send_monarch(ctx.peer, 1, "DRIP_FEED")
        assert_receive {:vws_event, _, :dnc_progress, %{operation: :download_execute}}, 10_000

        # the simulated machine takes the block from its link a moment after the link acknowledged it
        assert eventually(fn -> GE2000.drip(ctx.sim) != nil end)

        samples = sample_while_running(ctx, [])
        assert length(samples) > 10

        for {monarch, program} <- samples do
          assert monarch == "ACTIVE"
          assert program == "004711"
        end

        assert finished(ctx.peer) == "0001DONE"
      end

      # MONARCH's status and program, read before the machine's state: every sample taken while the
      # simulated GE-2000 still feeds or drains the program must say ACTIVE.
      defp sample_while_running(ctx, acc) do
        monarch = Vws.CEC.SunComm.Status.answer(ctx.ws, "MONARCH")
        {%{program: program}, _age} = Mailbox.readings(ctx.ws).monarch

        case GE2000.drip(ctx.sim) do
          %{state: state} when state in [:feeding, :draining] ->
            Process.sleep(20)
            sample_while_running(ctx, [{monarch, program} | acc])

          _ended ->
            acc
        end
      end

      @tag baud: 9_600, feed_rate: 300, link: [reply_timeout: 2_000]
      test "a machine slower than the paced line: its buffer never runs empty", ctx do
        text = with_nc_file(ctx, 3 * @memory)
        assert monarch(ctx.peer, 1, "DRIP_FEED", 120_000) == "0001DONE"
        drip = assert_fed_exactly(ctx.sim, text)
        assert drip.underruns == 0
      end
    end
  end
end
