# One module per transfer kind (each with its own workstation and relay) so that the two run at
# once: together, one after the other, they were among the last modules of the suite.
for kind <- [:download, :upload] do
  defmodule Module.concat(Vws.Reliability.WCBitFlipTest, Macro.camelize("#{kind}")) do
    @kind kind
    @moduledoc """
    NC line transfers on the WC link under bit errors (issue 15, PROTOCOLS.md §1 "NC download",
    "NC upload"): for every single-bit flip in every byte of a transfer's traffic, in both
    directions — and for random bursts — the program arrives unchanged or the Monarch command ends
    `ERROR` with a reason; never `DONE` with other bytes. A real `Vws.Peers.WC.Client` talks to a real
    SUN_COMM over TCP through `Vws.Test.FlipRelay`.

    Before the lines were numbered and answered `Annnn`+BCC, one flip of `A` (0x41) into `E`
    (0x45) stored a line twice and the command ended DONE.
    """
    use ExUnit.Case, async: true
    use Vws.PropCase

    alias Vws.CEC.{Mailbox, SunComm}
    alias Vws.Test.{FlipRelay, Workstation}
    alias Vws.Peers.WC.Client

    @moduletag timeout: 600_000

    @program ["%", "O000012", "G1X1", "%"]

    setup do
      %{ws: ws} =
        Workstation.start(
          wc: "tcp://127.0.0.1:0",
          sun_comm: [partial_line_timeout: 40, upload_timeout: 150, download_timeout: 5_000]
        )

      wc = await_listening(ws)
      {:ok, relay} = FlipRelay.start_link(to_string(wc))
      %{ws: ws, relay: relay, via: FlipRelay.endpoint(relay)}
    end

    defp await_listening(ws) do
      case SunComm.listening(ws) do
        nil -> Process.sleep(10) && await_listening(ws)
        endpoint -> endpoint
      end
    end

    test "#{kind}: every single-bit flip in every byte, both directions", ctx do
      kind = @kind
      {to_target, to_client} = traffic(ctx, kind)
      assert to_target > 50 and to_client > 20

      flips =
        for {dir, n} <- [to_target: to_target, to_client: to_client],
            index <- 0..(n - 1),
            bit <- 0..7,
            do: {dir, index, Bitwise.bsl(1, bit)}

      outcomes =
        flips
        |> Enum.with_index(2)
        |> Enum.map(fn {flip, run} -> check!(ctx, kind, run, [flip]) end)

      # the flips made a difference: some transfers needed resends, some ended ERROR — and
      # every one that ended DONE carried the program exactly (checked in check!/4)
      assert Enum.count(outcomes, &(&1 == :done)) > length(flips) / 2
    end

    test "#{kind}: random bursts (several bits of a byte, or a run of up to 8 bits across two)",
         ctx do
      kind = @kind
      {to_target, to_client} = traffic(ctx, kind)
      counter = :counters.new(1, [])

      burst =
        :proper_types.bind(
          :proper_types.tuple([
            :proper_types.elements([:to_target, :to_client]),
            :proper_types.range(0, 1_000_000),
            :proper_types.range(2, 8),
            :proper_types.range(0, 7)
          ]),
          fn {dir, r, length, first_bit} ->
            n = if dir == :to_target, do: to_target, else: to_client
            index = rem(r, n)
            # `length` bits from `first_bit` on, as they follow on the serial line (LSB first)
            bits = for b <- first_bit..(first_bit + length - 1), do: b
            low = for b <- bits, b < 8, reduce: 0, do: (m -> Bitwise.bor(m, Bitwise.bsl(1, b)))

            high =
              for b <- bits, b >= 8, reduce: 0, do: (m -> Bitwise.bor(m, Bitwise.bsl(1, b - 8)))

            flips =
              [{dir, index, low}] ++
                if(high > 0 and index + 1 < n, do: [{dir, index + 1, high}], else: [])

            :proper_types.exactly(flips)
          end,
          false
        )

      property =
        :proper.forall(burst, fn flips ->
          :counters.add(counter, 1, 1)
          check!(ctx, kind, 5_000 + :counters.get(counter, 1), flips) in [:done, :error]
        end)

      assert_property(property, 150)
    end

    # The bytes of one clean transfer, per direction.
    defp traffic(ctx, kind) do
      :ok = FlipRelay.plan(ctx.relay, {:bytes, []})
      assert check!(ctx, kind, 1, []) == :done
      counts = FlipRelay.counts(ctx.relay)
      {counts.to_target, counts.to_client}
    end

    # One transfer as run number `run` (its own sequence and command number, so no string is
    # taken for a resend of another run's) with `flips` on the line. The verdict: `:done` with the
    # program exactly, or `:error` with a reason; anything else fails the test.
    defp check!(ctx, kind, run, flips) do
      ws = ctx.ws
      :ok = Mailbox.put_nc_file(ws, [])
      :ok = Mailbox.put_nc_up(ws, if(kind == :upload, do: @program, else: []))
      :ok = FlipRelay.plan(ctx.relay, {:bytes, flips})
      number = rem(run, 9_000) + 1

      {:ok, client} =
        Client.connect(ctx.via,
          sequence: rem(run, 10_000),
          numbers: %{"M" => number},
          reply_timeout: 150,
          line_timeout: 150
        )

      result =
        case kind do
          :download -> Client.download_program(client, @program)
          :upload -> Client.upload_program(client)
        end

      Client.close(client)
      # the link closed: a transfer still under way at the CEC ends now
      status = settled(ws, number)

      case {status, result} do
        {{^number, :done}, _} when kind == :download ->
          assert Mailbox.nc_file(ws) == @program, "DONE with other bytes, flips #{inspect(flips)}"
          :done

        {{^number, :done}, {:ok, _, lines}} ->
          assert lines == @program, "DONE with other bytes, flips #{inspect(flips)}"
          :done

        {{^number, :done}, other} ->
          flunk("UPLOAD_SUN DONE but the WC has #{inspect(other)}, flips #{inspect(flips)}")

        {{^number, {:error, reason}}, result} when is_binary(reason) and reason != "" ->
          assert Mailbox.nc_file(ws) == []
          # whatever the WC took, it took nothing else than the program
          with {:ok, _, lines} <- result, do: assert(lines == @program)
          :error

        {other, result} ->
          flunk("status #{inspect(other)}, WC #{inspect(result)}, flips #{inspect(flips)}")
      end
    end

    defp settled(ws, number, tries \\ 500) do
      case Mailbox.command_status(ws, :monarch) do
        {^number, :executing} when tries > 0 ->
          Process.sleep(10) && settled(ws, number, tries - 1)

        other ->
          other
      end
    end
  end
end
