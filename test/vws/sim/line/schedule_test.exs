defmodule Vws.Sim.Line.ScheduleTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  import :proper_types

  alias Vws.Sim.Line.Schedule

  doctest Schedule

  defp take!(s, now) do
    {out, n, next, s} = Schedule.take(s, now)
    out = IO.iodata_to_binary(out)
    assert byte_size(out) == n
    {out, next, s}
  end

  describe "pacing" do
    test "bits per byte: 8N1 is 10, parity adds one, a second stop bit one more" do
      assert Schedule.bits_per_byte(Schedule.new()) == 10
      assert Schedule.bits_per_byte(Schedule.new(parity: :even)) == 11
      assert Schedule.bits_per_byte(Schedule.new(parity: :odd, stop_bits: 2)) == 12
      assert Schedule.transmit_us(Schedule.new(baud: 4800, parity: :even), 480) == 1_100_000
    end

    test "960 bytes at 9600 Bd: none before its time, all after one second" do
      s = Schedule.push(Schedule.new(baud: 9600), :binary.copy("x", 960), 0)
      {out, next, s} = take!(s, 999_999)
      assert byte_size(out) == 959
      assert next == 1_000_000
      {out, nil, _} = take!(s, 1_000_000)
      assert out == "x"
    end

    test "an idle line gives no credit: bytes start when they arrive" do
      s = Schedule.new(baud: 9600)
      s = Schedule.push(s, "a", 0)
      {"a", nil, s} = take!(s, 10_000_000)
      s = Schedule.push(s, "bcdef", 10_000_000)
      {"", next, s} = take!(s, 10_001_000)
      assert next == 10_001_042
      {"bc", _, _} = take!(s, 10_002_100)
    end

    test "property: bytes never come out faster than the line carries them, and all come out in order" do
      gen = {
        range(1, 4),
        list({range(0, 3_000), binary()}),
        list(range(0, 5_000))
      }

      assert_property(
        :proper.forall(gen, fn {speed, pushes, takes} ->
          baud = Enum.at([1200, 4800, 9600, 115_200], speed - 1)
          check_pacing(baud, pushes, takes)
        end),
        150
      )
    end
  end

  # Pushes and takes interleaved at increasing times; checks after every take that the bytes
  # out since the first push fit in the line time elapsed (busy periods only lengthen it).
  defp check_pacing(baud, pushes, takes) do
    s = Schedule.new(baud: baud)
    bits = Schedule.bits_per_byte(s)
    events = merge(pushes, takes)

    {s, out, _t, _first, ok} =
      Enum.reduce(events, {s, [], 0, nil, true}, fn
        {:push, dt, bytes}, {s, out, t, first, ok} ->
          t = t + dt
          first = if first == nil and bytes != "", do: t, else: first
          {Schedule.push(s, bytes, t), out, t, first, ok}

        {:take, dt}, {s, out, t, first, ok} ->
          t = t + dt
          {taken, n, _next, s} = Schedule.take(s, t)
          out = [out | taken]
          total = IO.iodata_length(out)
          allowed = if first, do: div((t - first) * baud, bits * 1_000_000), else: 0
          {s, out, t, first, ok and n >= 0 and total <= allowed}
      end)

    {rest, _, nil, _} = Schedule.take(s, 10_000_000_000)
    sent = for {_, bytes} <- pushes, into: "", do: bytes
    ok and IO.iodata_to_binary([out | rest]) == sent
  end

  defp merge([], takes), do: Enum.map(takes, &{:take, &1})
  defp merge(pushes, []), do: Enum.map(pushes, fn {dt, b} -> {:push, dt, b} end)

  defp merge([{dt, b} | pushes], [t | takes]),
    do: [{:push, dt, b}, {:take, t} | merge(pushes, takes)]

  describe "delay and jitter" do
    test "a fixed delay holds every chunk exactly that long" do
      s = Schedule.new(delay: 50)
      s = Schedule.push(s, "ab", 1_000)
      {"", 51_000, s} = take!(s, 50_999)
      {"ab", nil, _} = take!(s, 51_000)
    end

    test "jitter stays within 0..jitter ms and never reorders" do
      s = Schedule.new(delay: 10, jitter: 20, seed: 4)
      s = Enum.reduce(0..199, s, fn i, s -> Schedule.push(s, <<i>>, i * 100) end)

      out = drain(s, 0, [])
      assert Enum.map(out, &elem(&1, 0)) == Enum.to_list(0..199)

      Enum.reduce(out, 0, fn {i, at}, previous ->
        pushed = i * 100
        assert at >= pushed + 10_000
        assert at <= max(pushed + 30_000, previous)
        at
      end)
    end

    test "jitter draws are deterministic from the seed" do
      times = fn seed ->
        s = Schedule.new(jitter: 100, seed: seed)

        Enum.map_reduce(1..20, s, fn i, s ->
          s = Schedule.push(s, "x", i * 1_000_000)
          {_, next, s} = take!(s, i * 1_000_000)
          {_, nil, s} = take!(s, next)
          {next - i * 1_000_000, s}
        end)
        |> elem(0)
      end

      assert times.(1) == times.(1)
      assert times.(1) != times.(2)
      assert Enum.all?(times.(1), &(&1 in 0..100_000))
    end
  end

  # Takes at each due time; returns {byte, time out} in order.
  defp drain(s, t, acc) do
    {out, next, s} = take!(s, t)
    acc = Enum.reverse(for(<<b <- out>>, do: {b, t}), acc)
    if next, do: drain(s, next, acc), else: Enum.reverse(acc)
  end

  describe "configure" do
    test "a new baud rate applies from the next byte; bytes out stay out" do
      s = Schedule.push(Schedule.new(baud: 9600), :binary.copy("x", 100), 0)
      {out, _, s} = take!(s, 10_417)
      assert byte_size(out) == 10
      s = Schedule.configure(s, baud: 960)
      # the remaining 90 bytes now take about 10.4 ms each
      {out, _, s} = take!(s, 10_417 + 20_000)
      assert byte_size(out) == 1
      {out, nil, _} = take!(s, 10_417 + 937_500)
      assert byte_size(out) == 89
      assert Schedule.settings(s)[:baud] == 960
    end

    test "no pacing without a baud rate" do
      s = Schedule.push(Schedule.new(), :binary.copy("y", 1_000_000), 5)
      {out, nil, s} = take!(s, 5)
      assert byte_size(out) == 1_000_000
      assert Schedule.queued(s) == 0
    end

    test "out-of-range settings raise" do
      assert_raise ArgumentError, fn -> Schedule.new(baud: 0) end
      assert_raise ArgumentError, fn -> Schedule.new(parity: :mark) end
      assert_raise ArgumentError, fn -> Schedule.new(delay: -1) end
    end
  end

  describe "random cuts" do
    test "none without a rate; intervals average 1/rate" do
      assert {:infinity, _} = Schedule.cut_interval(Schedule.new())

      {ms, _} =
        Enum.map_reduce(1..2_000, Schedule.new(disconnect_rate: 4, seed: 9), fn _, s ->
          Schedule.cut_interval(s)
        end)

      mean = Enum.sum(ms) / length(ms)
      # exponential, mean 250 ms; 2000 samples: sd of the mean about 5.6 ms
      assert mean > 220 and mean < 280
    end
  end
end
