defmodule Vws.Sim.Line.Counters do
  @moduledoc false
  # The counters of one Vws.Sim.Line, in an :atomics-backed :counters array that every pump and
  # session of the line adds to directly, so info/1 is live without asking each connection.
  # `queued` is a gauge: bytes waiting in the line, summed over its connections.

  @direction_keys [:bytes_in, :bytes_out, :bits_flipped, :bytes_dropped, :overruns, :queued]
  @line_keys [:connections, :disconnects, :closes, :connect_failures]

  @index (for({key, i} <- Enum.with_index(@direction_keys, 1), do: {{:to_target, key}, i}) ++
            for({key, i} <- Enum.with_index(@direction_keys, 7), do: {{:to_client, key}, i}) ++
            for({key, i} <- Enum.with_index(@line_keys, 13), do: {{:line, key}, i}))
         |> Map.new()

  @size map_size(@index)

  def new, do: :counters.new(@size, [:write_concurrency])

  def add(_counters, _dir, _key, 0), do: :ok
  def add(counters, dir, key, n), do: :counters.add(counters, Map.fetch!(@index, {dir, key}), n)

  def add(counters, key), do: add(counters, :line, key, 1)

  # Adds what a Faults.apply/2 changed between two Faults.counters/1 readings.
  def add_faults(counters, dir, before, after_) do
    add(counters, dir, :bytes_in, after_.bytes_in - before.bytes_in)
    add(counters, dir, :bits_flipped, after_.bits_flipped - before.bits_flipped)
    add(counters, dir, :bytes_dropped, after_.bytes_dropped - before.bytes_dropped)
  end

  def read(counters) do
    direction = fn dir ->
      Map.new(@direction_keys, &{&1, :counters.get(counters, Map.fetch!(@index, {dir, &1}))})
    end

    line = Map.new(@line_keys, &{&1, :counters.get(counters, Map.fetch!(@index, {:line, &1}))})
    Map.merge(line, %{to_target: direction.(:to_target), to_client: direction.(:to_client)})
  end
end
