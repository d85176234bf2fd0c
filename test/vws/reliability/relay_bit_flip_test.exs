# The exhaustive flips in two modules, the even and the odd bytes of each direction (each
# module with its own floor and relay; the random bursts in the first), so that they run at
# once: one module was among the last of the suite.
for part <- [0, 1] do
  defmodule Module.concat(Vws.Reliability.RelayBitFlipTest, "Part#{part + 1}") do
    @part part
    @moduledoc """
    Relay writes under bit errors on the HPIB link to DAQ #1 (issue 15, PROTOCOLS.md §4 "Relays are
    verified whole"): for every single-bit flip in every byte of an actuation's traffic, both
    directions — and random bursts — VWS_STATUS's actuation (the path every vise, gripper, vacuum
    and cycle-start command takes) ends `:ok` only with every relay of the slot as intended: the
    commanded one set, every other one as it was. Otherwise it ends with a reason.

    Before, `ROUT:CLOS (@207)` arriving as `(@206)` closed the vise during `V ON` and the read-back
    of channel 207 alone said nothing was wrong.
    """
    use ExUnit.Case, async: true
    use Vws.PropCase

    alias Vws.Partitions.VwsStatus
    alias Vws.Sim.Plant
    alias Vws.Test.{FlipRelay, RelayDAQ}

    @moduletag timeout: 600_000

    @slot Enum.to_list(201..210)
    # the slot before each actuation: the gripper's open solenoid and the vise's open valve on
    @before [201, 205]

    # no polls: the traffic is the actuation's alone
    setup do: RelayDAQ.start(timeout_ms: 150)

    test "V ON: every single-bit flip in every #{if part == 0, do: "even", else: "odd"} byte, both directions",
         ctx do
      {to_target, to_client} = traffic(ctx)

      flips =
        for {dir, n} <- [to_target: to_target, to_client: to_client],
            index <- 0..(n - 1),
            rem(index, 2) == @part,
            bit <- 0..7,
            do: {dir, index, Bitwise.bsl(1, bit)}

      outcomes = Enum.map(flips, &check!(ctx, [&1]))
      assert Enum.count(outcomes, &(&1 == :ok)) > length(flips) / 2
    end

    if part == 0 do
      test "V ON: random bursts", ctx do
        {to_target, to_client} = traffic(ctx)

        burst = Vws.Test.FlipRelay.burst(to_target, to_client)

        assert_property(
          :proper.forall(burst, &checked(fn -> check!(ctx, &1) in [:ok, :error] end)),
          150
        )
      end
    end

    defp traffic(ctx) do
      assert check!(ctx, []) == :ok
      counts = FlipRelay.counts(ctx.relay)

      assert counts.to_target > 60 and counts.to_client > 40,
             "a clean V ON: #{inspect(counts)} bytes on the line (a run under load saw fewer)"

      {counts.to_target, counts.to_client}
    end

    # The slot set to @before on the plant itself, then VACUUM's relay (207) closed through
    # VWS_STATUS with `flips` on the line. `:ok` only with the whole slot as intended.
    defp check!(ctx, flips) do
      for ch <- @slot do
        if ch in @before,
          do: :ok = Plant.close_channel(ctx.plant, {:daq1, ch}),
          else: :ok = Plant.open_channel(ctx.plant, {:daq1, ch})
      end

      :ok = FlipRelay.plan(ctx.relay, {:bytes, flips})

      case VwsStatus.actuate(ctx.ws, vacuum_motor: :close) do
        :ok ->
          assert closed(ctx.plant) == Enum.sort([207 | @before]),
                 "DONE with other relays, flips #{inspect(flips)}"

          :ok

        {:error, reason} when is_binary(reason) and reason != "" ->
          :error

        other ->
          flunk("#{inspect(other)}, flips #{inspect(flips)}")
      end
    end

    defp closed(plant) do
      for {:daq1, ch} <- Plant.snapshot(plant).relays, ch in @slot, do: ch
    end
  end
end
