defmodule Vws.Sim.Line.FaultsTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  import Bitwise

  alias Vws.Sim.Line.Faults

  doctest Faults

  # A fixed pseudo-random input, the same on every run.
  defp input(size, seed \\ 1) do
    rand = :rand.seed_s(:exsss, {seed, 2, 3})
    {bytes, _} = Enum.map_reduce(1..size, rand, fn _, r -> :rand.uniform_s(256, r) end)
    :erlang.list_to_binary(Enum.map(bytes, &(&1 - 1)))
  end

  defp run(bytes, opts), do: bytes |> Faults.apply(Faults.new(opts)) |> elem(0)

  defp feed_chunks(chunks, faults) do
    {outs, faults} = Enum.map_reduce(chunks, faults, &Faults.apply/2)
    {IO.iodata_to_binary(outs), faults}
  end

  defp differing_bits(a, b) do
    for(<<x <- :crypto.exor(a, b)>>, do: popcount(x)) |> Enum.sum()
  end

  defp popcount(0), do: 0
  defp popcount(x), do: (x &&& 1) + popcount(x >>> 1)

  describe "no faults" do
    test "bytes pass unchanged and are counted" do
      bytes = input(10_000)
      {out, faults} = Faults.apply(bytes, Faults.new(seed: 3))
      assert out == bytes

      assert Faults.counters(faults) ==
               %{bytes_in: 10_000, bytes_out: 10_000, bits_flipped: 0, bytes_dropped: 0}
    end
  end

  describe "determinism" do
    test "the same seed and input give the same output" do
      bytes = input(50_000)
      opts = [seed: 99, ber: 1.0e-3, drop: 1.0e-3]
      assert run(bytes, opts) == run(bytes, opts)
      assert run(bytes, opts) != bytes
    end

    test "different seeds give different damage" do
      bytes = input(50_000)
      outs = for seed <- 1..5, do: run(bytes, seed: seed, ber: 1.0e-3, drop: 1.0e-3)
      assert length(Enum.uniq(outs)) == 5
    end

    test "seeds may be any term" do
      bytes = input(5_000)
      assert run(bytes, seed: {:x, 1}, ber: 0.01) == run(bytes, seed: {:x, 1}, ber: 0.01)
      assert run(bytes, seed: {:x, 1}, ber: 0.01) != run(bytes, seed: {:x, 2}, ber: 0.01)
    end

    test "the output does not depend on how the input is cut into chunks" do
      gen = {:proper_types.binary(), :proper_types.list(:proper_types.range(1, 40))}

      assert_property(
        :proper.forall(gen, fn {bytes, cuts} ->
          opts = [seed: byte_size(bytes), ber: 0.05, drop: 0.05, disconnect_after: 300]
          {whole, f1} = Faults.apply(bytes, Faults.new(opts))

          {pieces, f2} =
            feed_chunks(Vws.Codecs.WC.Generators.chunks(bytes, cuts), Faults.new(opts))

          whole == pieces and Faults.counters(f1) == Faults.counters(f2)
        end),
        200
      )
    end
  end

  describe "bit errors" do
    test "1e6 bits at BER 1e-3: the flips are within a wide binomial band and all counted" do
      bytes = input(125_000)
      {out, faults} = Faults.apply(bytes, Faults.new(seed: 7, ber: 1.0e-3))
      flips = differing_bits(bytes, out)
      # n = 1e6, p = 1e-3: mean 1000, standard deviation 31.6; the band is more than 6 of them.
      assert flips in 800..1200
      assert Faults.counters(faults).bits_flipped == flips
      assert byte_size(out) == byte_size(bytes)
    end

    test "every data bit position is hit about equally" do
      bytes = :binary.copy(<<0>>, 100_000)
      out = run(bytes, seed: 11, ber: 1.0e-2)

      per_bit =
        for bit <- 0..7 do
          Enum.count(:binary.bin_to_list(out), &((&1 >>> bit &&& 1) == 1))
        end

      # 1e5 trials per position at p = 0.01: mean 1000, sd 31.5
      assert Enum.all?(per_bit, &(&1 in 800..1200)), inspect(per_bit)
    end

    test "BER 1 inverts every bit, BER 0 none" do
      bytes = input(1_000)
      assert run(bytes, ber: 1.0) == :crypto.exor(bytes, :binary.copy(<<0xFF>>, 1_000))
      assert run(bytes, ber: 0) == bytes
    end
  end

  describe "lost bytes" do
    test "1e5 bytes at p = 1e-2: the losses are within a wide binomial band" do
      bytes = input(100_000)
      {out, faults} = Faults.apply(bytes, Faults.new(seed: 5, drop: 1.0e-2))
      lost = byte_size(bytes) - byte_size(out)
      # mean 1000, sd 31.5
      assert lost in 800..1200
      assert Faults.counters(faults).bytes_dropped == lost
    end

    test "what is left is the input with some bytes taken out, in order" do
      bytes = input(2_000)
      out = run(bytes, seed: 8, drop: 0.1)
      assert subsequence?(:binary.bin_to_list(out), :binary.bin_to_list(bytes))
    end

    test "drop 1 loses everything" do
      assert run(input(100), drop: 1) == ""
    end
  end

  defp subsequence?([], _), do: true
  defp subsequence?(_, []), do: false
  defp subsequence?([x | xs], [x | ys]), do: subsequence?(xs, ys)
  defp subsequence?(xs, [_ | ys]), do: subsequence?(xs, ys)

  describe "cut after N bytes" do
    test "the N-th byte passes, nothing after it; later input is not counted" do
      faults = Faults.new(disconnect_after: 10)
      {"0123", faults} = Faults.apply("0123", faults)
      refute Faults.cut?(faults)
      {"456789", faults} = Faults.apply("456789abc", faults)
      assert Faults.cut?(faults)
      {"", faults} = Faults.apply("more", faults)
      assert Faults.counters(faults).bytes_in == 10
    end

    test "set at run time, it counts from then" do
      {_, faults} = Faults.apply(input(100), Faults.new())
      faults = Faults.configure(faults, disconnect_after: 3)
      assert {"abc", _} = Faults.apply("abcdef", faults)
      faults = Faults.configure(faults, disconnect_after: nil)
      assert {"abcdef", _} = Faults.apply("abcdef", faults)
    end
  end

  describe "configure" do
    test "faults change at run time and settings/1 reports them" do
      faults = Faults.new(seed: 1)
      {out, faults} = Faults.apply("abc", faults)
      assert out == "abc"
      faults = Faults.configure(faults, ber: 1.0)
      assert {<<0x9E, 0x9D, 0x9C>>, faults} = Faults.apply("abc", faults)
      assert Faults.settings(faults) == [ber: 1.0, drop: 0.0, disconnect_after: nil]
    end

    test "out-of-range values are programmer errors" do
      assert_raise ArgumentError, fn -> Faults.new(ber: 1.5) end
      assert_raise ArgumentError, fn -> Faults.new(drop: -0.1) end
      assert_raise ArgumentError, fn -> Faults.new(disconnect_after: 0) end
    end
  end

  describe "gap/2" do
    test "geometric with the right mean, also for tiny p" do
      for p <- [0.5, 1.0e-3, 1.0e-9] do
        {gaps, _} =
          Enum.map_reduce(1..4_000, :rand.seed_s(:exsss, {1, 2, 3}), fn _, r ->
            Faults.gap(p, r)
          end)

        mean = Enum.sum(gaps) / length(gaps)
        expected = (1 - p) / p
        # 4000 samples: the mean's sd is about expected / 63
        assert abs(mean - expected) < 0.1 * expected + 1, "p=#{p} mean=#{mean}"
      end
    end
  end
end
