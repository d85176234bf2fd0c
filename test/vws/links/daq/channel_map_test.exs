defmodule Vws.Links.DAQ.ChannelMapTest do
  use ExUnit.Case, async: true

  alias Vws.Links.DAQ.ChannelMap

  doctest ChannelMap

  @config ChannelMap.load()

  test "the channel map is checked" do
    assert ChannelMap.channel(@config, :table_park) == {:daq1, 104}
    assert ChannelMap.channel(@config, :nothing) == nil

    assert_raise ArgumentError, ~r/daq1 channel 118/, fn ->
      ChannelMap.load(%{daq1: %{118 => %{kind: :switch, signal: :vise_jaw_mm}}})
    end

    assert_raise ArgumentError, ~r/two channels/, fn ->
      ChannelMap.load(%{daq1: %{118 => %{kind: :switch, signal: :table_park}}})
    end

    assert_raise ArgumentError, ~r/volts_per_unit/, fn ->
      ChannelMap.load(%{daq1: %{103 => %{kind: :pot, signal: :vise_jaw_mm, volts_per_unit: nil}}})
    end
  end

  test "every signal of the shipped map is wired exactly once" do
    wired = @config.channels |> Map.values() |> Enum.map(& &1.signal) |> Enum.sort()
    # :spare is a kind no shipped channel uses any more (116 became CHANGER_1's switch)
    known =
      ChannelMap.signals() |> Map.values() |> Enum.concat() |> List.delete(:spare) |> Enum.sort()

    assert wired == known

    assert Enum.count(@config.channels, fn {{daq, ch}, _} -> daq == :daq1 and ch in 101..116 end) ==
             16
  end
end
