# DOWNLOAD_GE, UPLOAD_GE and DRIP_FEED under bit errors on the DNC link (issue 15; the floor and
# the checks are Vws.Test.DNCFlip's): every single-bit flip in every byte of a transfer's
# traffic, both directions, and random bursts — the program arrives unchanged or the command
# ends ERROR with a reason, never DONE with other bytes. One module per test, each with its own
# GE-2000 and workstation, so that they run at once (each spends most of its time waiting out
# the link's timeouts, not on a core).
for kind <- [:download, :upload] do
  name = kind |> Atom.to_string() |> Macro.camelize()

  defmodule Module.concat(Vws.Reliability.DNCBitFlipTest, "#{name}SingleBit") do
    use Vws.Test.DNCFlip
    @kind kind

    test "#{kind}: single-bit flips in every byte, both directions", ctx do
      {to_target, to_client} = DNCFlip.traffic(ctx, @kind)

      flips =
        for {dir, n} <- [to_target: to_target, to_client: to_client],
            index <- 0..(n - 1),
            bit <- 0..7,
            do: {dir, index, Bitwise.bsl(1, bit)}

      outcomes = Enum.map(flips, &DNCFlip.check!(ctx, @kind, [&1]))
      assert Enum.count(outcomes, &(&1 == :done)) > length(flips) / 2
    end
  end

  defmodule Module.concat(Vws.Reliability.DNCBitFlipTest, "#{name}Bursts") do
    use Vws.Test.DNCFlip
    @kind kind

    test "#{kind}: random bursts", ctx do
      {to_target, to_client} = DNCFlip.traffic(ctx, @kind)
      burst = Vws.Test.FlipRelay.burst(to_target, to_client)

      property =
        :proper.forall(
          burst,
          &checked(fn -> DNCFlip.check!(ctx, @kind, &1) in [:done, :error] end)
        )

      assert_property(property, 120)
    end
  end
end

defmodule Vws.Reliability.DNCBitFlipTest.DripFeedBursts do
  use Vws.Test.DNCFlip

  # Drip feed (E): the machine runs the program while it arrives; a line fault never makes it
  # skip or repeat a block — DONE: it ran exactly the program; ERROR: it ran a prefix of it.
  test "drip feed: random bursts", ctx do
    {to_target, to_client} = DNCFlip.traffic(ctx, :drip_feed)
    burst = Vws.Test.FlipRelay.burst(to_target, to_client)

    property =
      :proper.forall(
        burst,
        &checked(fn -> DNCFlip.check!(ctx, :drip_feed, &1) in [:done, :error] end)
      )

    assert_property(property, 60)
  end
end
