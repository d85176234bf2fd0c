defmodule Vws.Partitions.VwsStatus.SheddingTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Partitions.VwsStatus
  alias Vws.Partitions.VwsStatus.Shedding
  alias Vws.Test.DAQFloor

  doctest Shedding

  @opts [high: 0.10, low: 0.02, calm: 4, max_stretch: 5]

  defp sample_gen do
    :proper_types.bind(
      :proper_types.integer(0, 2_000),
      fn due ->
        :proper_types.bind(
          :proper_types.integer(0, due),
          fn bad ->
            :proper_types.bind(
              :proper_types.integer(0, bad),
              fn late -> %{due: due, late: late, missed: bad - late} end,
              false
            )
          end,
          false
        )
      end,
      false
    )
  end

  describe "the policy" do
    test "property: the stretch stays within 1..max_stretch whatever the samples" do
      assert_property(
        :proper.forall(:proper_types.list(sample_gen()), fn samples ->
          states = Enum.scan(samples, %{stretch: 1, calm: 0}, &Shedding.next(&2, &1, @opts))
          Enum.all?(states, &(&1.stretch in 1..5))
        end)
      )
    end

    test "property: an overloaded interval never lowers the stretch and raises it below the cap" do
      assert_property(
        :proper.forall({:proper_types.integer(1, 5), sample_gen()}, fn {k, sample} ->
          next = Shedding.next(%{stretch: k, calm: 0}, sample, @opts)
          bad = sample.late + sample.missed

          cond do
            sample.due == 0 -> next.stretch == k
            bad > 0.10 * sample.due -> next.stretch == min(5, max(k + 1, ceil(k * 1.5)))
            true -> next.stretch <= k
          end
        end)
      )
    end

    test "property: after `calm` quiet intervals in a row the stretch comes down by one, never below 1" do
      assert_property(
        :proper.forall({:proper_types.integer(1, 5), :proper_types.integer(1, 1_000)}, fn {k, due} ->
          quiet = %{due: due, late: 0, missed: 0}

          states =
            Enum.scan(1..4, %{stretch: k, calm: 0}, fn _, s -> Shedding.next(s, quiet, @opts) end)

          Enum.map(states, & &1.stretch) == [k, k, k, max(k - 1, 1)]
        end)
      )
    end

    test "property: every workstation of a pool polls at the same period, between poll_ms and the cap" do
      assert_property(
        :proper.forall(
          {:proper_types.integer(1, 100), :proper_types.integer(1, 50),
           :proper_types.integer(1, 1_000), :proper_types.integer(1, 200)},
          fn {poll_ms, stretch, max_period, n} ->
            periods = for _ws <- 1..n, do: Shedding.period(poll_ms, stretch, max_period)

            length(Enum.uniq(periods)) == 1 and hd(periods) >= poll_ms and
              hd(periods) <= max(max_period, poll_ms) and
              hd(periods) <= max(poll_ms * stretch, poll_ms)
          end
        )
      )
    end
  end

  describe "a governor" do
    # its intervals driven by hand: a sample taken, then the governor's state read
    defp interval(governor) do
      send(governor, :sample)
      :sys.get_state(governor)
    end

    test "stretches its pool's polls when they go late, and relaxes them when they are on time" do
      pool = {:shedding_test, make_ref()}
      governor = start_supervised!({Shedding, pool: pool, interval_ms: 3_600_000, calm: 1})
      assert Shedding.stretch(pool) == 1

      Shedding.count(pool, 100, 50, 10)
      interval(governor)
      assert Shedding.stretch(pool) == 2
      # the counts were taken: an interval without polls changes nothing
      interval(governor)
      assert Shedding.stretch(pool) == 2

      Shedding.count(pool, 100, 1, 0)
      interval(governor)
      assert Shedding.stretch(pool) == 1
    end

    test "leaves a held stretch alone until it is released" do
      pool = {:shedding_test, make_ref()}
      governor = start_supervised!({Shedding, pool: pool, interval_ms: 3_600_000, calm: 1})
      :ok = Shedding.hold(pool, 4)
      Shedding.count(pool, 100, 0, 0)
      interval(governor)
      assert Shedding.stretch(pool) == 4

      :ok = Shedding.release(pool)
      Shedding.count(pool, 100, 0, 0)
      interval(governor)
      assert Shedding.stretch(pool) == 3
    end
  end

  describe "VWS_STATUS under shedding" do
    test "polls at the stretched period, never longer than half the staleness limit" do
      pool = {:shedding_test, make_ref()}
      :ok = Shedding.hold(pool, 1_000)

      %{ws: ws} =
        DAQFloor.start(
          vws_status: [poll_ms: 10, stale_after_ms: 120, shedding: pool, max_period_ms: 500]
        )

      assert VwsStatus.stats(ws).period_ms == 60
      :ok = Shedding.hold(pool, 3)
      assert VwsStatus.stats(ws).period_ms == 30
      # it still reads DAQ #1
      assert Vws.Test.Eventually.eventually(fn -> match?({:ok, _}, VwsStatus.readings(ws)) end)
    end

    test "a command awaiting a fresh reading ends ERROR in words rather than take an older one" do
      pool = {:shedding_test, make_ref()}
      :ok = Shedding.hold(pool, 1_000)

      # one poll in 20 s: the first reading comes, the next not within the await
      %{ws: ws} =
        DAQFloor.start(
          vws_status: [poll_ms: 20, stale_after_ms: 60_000, shedding: pool, max_period_ms: 20_000]
        )

      assert Vws.Test.Eventually.eventually(fn -> match?({:ok, _}, VwsStatus.readings(ws)) end)
      assert VwsStatus.stats(ws).period_ms == 20_000
      since = System.monotonic_time(:microsecond)

      assert VwsStatus.await(ws, since, 100, fn _r -> :ok end) ==
               {:error, "DAQ #1 NOT ANSWERING (NO FRESH READING IN 100 MS)"}
    end
  end
end
