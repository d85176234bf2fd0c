defmodule Vws.Links.DNC.PaceTest do
  use ExUnit.Case, async: true

  alias Vws.Links.DNC.Pace

  @limits %{max_text: 256, wack_delay: 2_000}

  test "before a rate is known the wait starts short and doubles with each WACK answering the ENQ, up to wack_delay" do
    {p, first} = Pace.wait(Pace.new(), false, @limits)
    {p, second} = Pace.wait(p, true, @limits)
    {_p, third} = Pace.wait(p, true, @limits)
    assert first < 100 and second == 2 * first and third == 2 * second

    waits =
      Enum.scan(1..10, {p, 0}, fn _, {p, _} -> Pace.wait(p, true, @limits) end)
      |> Enum.map(&elem(&1, 1))

    assert List.last(waits) == 2_000
  end

  test "the rate between moments of room again is learned, and the wait is one block's time at it" do
    # the machine runs 256 bytes a second: room again every second, a block sent each time
    p = Enum.reduce(0..5, Pace.new(), fn i, p -> Pace.released(p, 1_000 * i, 256 * i) end)

    assert_in_delta Pace.rate(p), 256.0, 0.01
    assert {_p, 1_000} = Pace.wait(p, false, @limits)
  end

  test "a WACK answering the ENQ with a rate known lowers the rate: the next wait is longer" do
    p = Pace.new() |> Pace.released(0, 0) |> Pace.released(1_000, 512)
    {p, w1} = Pace.wait(p, false, @limits)
    {_p, w2} = Pace.wait(p, true, @limits)
    assert w2 > w1
  end

  test "every wait stays within 20 ms and wack_delay, however fast or slow the machine" do
    fast = Pace.new() |> Pace.released(0, 0) |> Pace.released(1, 1_000_000)
    slow = Pace.new() |> Pace.released(0, 0) |> Pace.released(100_000, 1)
    assert {_, 20} = Pace.wait(fast, false, @limits)
    assert {_, 2_000} = Pace.wait(slow, false, @limits)
  end
end
