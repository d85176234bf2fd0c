defmodule Vws.Ops.MTConnect.BufferTest do
  # The agent's buffer alone, as plain data, against a list model: every observation ever
  # appended, in order, the i-th with sequence number i.
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Ops.MTConnect.Buffer

  doctest Buffer

  @ids ["a", "b", "c", "d"]

  # a buffer after `appends` (each {id, value}), and the model: every observation appended
  defp build(capacity, frequency, appends) do
    Enum.reduce(Enum.with_index(appends, 1), {Buffer.new(capacity, frequency), []}, fn
      {{id, value}, ts}, {b, all} ->
        seq = Buffer.next(b)
        {Buffer.append(b, id, value, ts), [{seq, id, value, ts} | all]}
    end)
    |> then(fn {b, all} -> {b, Enum.reverse(all)} end)
  end

  defp held(b, all) do
    %{first: first, last: last} = Buffer.sequences(b)
    Enum.filter(all, fn {seq, _, _, _} -> seq >= first and seq <= last end)
  end

  defp state(observations),
    do: Map.new(observations, fn {seq, id, value, ts} -> {id, {seq, value, ts}} end)

  defp appends, do: :proper_types.list({:proper_types.oneof(@ids), :proper_types.range(0, 9)})
  defp capacity, do: :proper_types.range(1, 12)
  defp frequency, do: :proper_types.range(1, 8)

  describe "sequence numbers (MTConnect: firstSequence, lastSequence, nextSequence)" do
    test "a new buffer: nothing held, the first observation gets 1" do
      b = Buffer.new(4)
      assert Buffer.sequences(b) == %{first: 1, last: 0, next: 1, size: 4}
      assert Buffer.range(b, 0, 10) == []
      assert Buffer.current(b) == %{}
      assert Buffer.latest(b, "a") == nil
    end

    test "each observation gets the next number; the buffer never holds more than its capacity" do
      property =
        :proper.forall({capacity(), frequency(), appends()}, fn {cap, freq, appends} ->
          Enum.reduce_while(appends, {Buffer.new(cap, freq), true}, fn {id, v}, {b, true} ->
            before = Buffer.sequences(b)
            b = Buffer.append(b, id, v, 0)
            after_ = Buffer.sequences(b)

            ok =
              after_.next == before.next + 1 and after_.last == before.next and
                after_.first >= before.first and after_.last - after_.first + 1 <= cap and
                length(Buffer.range(b, 0, after_.next + 5)) == after_.last - after_.first + 1 and
                Buffer.latest(b, id) == v

            {if(ok, do: :cont, else: :halt), {b, ok}}
          end)
          |> elem(1)
        end)

      assert_property(property, 300)
    end

    test "firstSequence is the oldest held: the last `capacity` observations are kept" do
      property =
        :proper.forall({capacity(), frequency(), appends()}, fn {cap, freq, appends} ->
          {b, all} = build(cap, freq, appends)
          n = length(all)

          Buffer.sequences(b) == %{first: max(1, n - cap + 1), last: n, next: n + 1, size: cap} and
            Buffer.range(b, 0, n + 1) == Enum.take(all, -cap)
        end)

      assert_property(property, 300)
    end
  end

  describe "current and current?at= against the model" do
    test "current is every data item's latest observation; state_at(at) its latest up to at" do
      property =
        :proper.forall({capacity(), frequency(), appends()}, fn {cap, freq, appends} ->
          {b, all} = build(cap, freq, appends)
          %{first: first, next: next} = Buffer.sequences(b)

          Buffer.current(b) == state(all) and
            Enum.all?((first - 2)..(next + 1), fn at ->
              case Buffer.state_at(b, at) do
                {:ok, state} ->
                  at >= first and at < next and
                    state == state(Enum.filter(all, &(elem(&1, 0) <= at)))

                {:error, {:out_of_range, "at", ^at, ^first, last}} ->
                  last == next - 1 and (at < first or at >= next)

                _ ->
                  false
              end
            end)
        end)

      assert_property(property, 300)
    end
  end

  describe "sample windows against the model" do
    # What the standard asks of a sample, said over the list of held observations.
    defp model_sample(b, all, from, count, to, keep) do
      %{first: first, next: next, size: cap} = Buffer.sequences(b)
      kept = b |> held(all) |> Enum.filter(&(elem(&1, 1) in keep))
      seq = &elem(&1, 0)

      cond do
        from != nil and (from < first or from > next) ->
          {:error, {:out_of_range, "from", from, first, next}}

        to != nil and (to <= (from || first) or to > next) ->
          {:error, {:out_of_range, "to", to, (from || first) + 1, next}}

        count == 0 ->
          {:error, :zero_count}

        to != nil and (count < 1 or count > cap) ->
          {:error, {:out_of_range, "count", count, 1, cap}}

        count < -cap or count > cap ->
          {:error, {:out_of_range, "count", count, -cap, cap}}

        to != nil ->
          rows = Enum.filter(kept, &(seq.(&1) >= (from || first) and seq.(&1) <= to))
          {:ok, Enum.take(rows, -count), min(to + 1, next)}

        count > 0 ->
          rows = Enum.filter(kept, &(seq.(&1) >= (from || first)))

          # the page ends after its count-th observation, or with the buffer
          if length(rows) >= count,
            do: {:ok, Enum.take(rows, count), seq.(Enum.at(rows, count - 1)) + 1},
            else: {:ok, rows, next}

        true ->
          rows = Enum.filter(kept, &(seq.(&1) <= (from || next - 1)))
          {:ok, Enum.take(rows, count), next}
      end
    end

    test "from, count and to select what the list model selects, or the same error" do
      param = fn -> :proper_types.oneof([nil, :proper_types.range(-3, 40)]) end

      property =
        :proper.forall(
          {capacity(), frequency(), appends(), param.(), :proper_types.range(-15, 15), param.(),
           :proper_types.non_empty(:proper_types.list(:proper_types.oneof(@ids)))},
          fn {cap, freq, appends, from, count, to, keep} ->
            {b, all} = build(cap, freq, appends)
            keep? = fn {_seq, id, _v, _ts} -> id in keep end
            got = Buffer.sample(b, from, count, to, keep?)
            want = model_sample(b, all, from, count, to, keep)

            got == want
          end
        )

      assert_property(property, 1000)
    end

    test "a page's nextSequence is where the next page starts: pages cover the buffer once" do
      property =
        :proper.forall(
          {capacity(), frequency(), appends(), :proper_types.range(1, 5)},
          fn {cap, freq, appends, count} ->
            {b, all} = build(cap, freq, appends)
            %{first: first, next: next} = Buffer.sequences(b)
            count = min(count, cap)

            pages =
              Stream.unfold(first, fn
                from when from >= next ->
                  nil

                from ->
                  {:ok, rows, after_} = Buffer.sample(b, from, count, nil)
                  {rows, after_}
              end)

            Enum.concat(pages) == held(b, all)
          end
        )

      assert_property(property, 300)
    end
  end
end
