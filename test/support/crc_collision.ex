defmodule Vws.Test.CRCCollision do
  @moduledoc """
  NC programs that the GE-2000's directory cannot tell apart: the same size and the same
  CRC-16/ARC, different bytes (issue 30 item 7). The CRC has 65,536 values, so among programs of
  one length that differ only in a few digits some share one after a few hundred tries
  (birthday); this searches in a fixed order, so the same programs come every time.

      iex> [a, b] = Vws.Test.CRCCollision.programs(7, 2)
      iex> {a != b, byte_size(a) == byte_size(b), Vws.Codecs.CRC16.compute(a) == Vws.Codecs.CRC16.compute(b)}
      {true, true, true}
  """

  @doc """
  `count` different programs numbered `number` (`"%\\nO<number>\\nN10 X<d.dddddd>\\n%\\n"`), all of
  one size and one CRC-16/ARC.
  """
  @spec programs(non_neg_integer, pos_integer) :: [binary]
  def programs(number, count) do
    Stream.iterate(0, &(&1 + 1))
    |> Stream.map(&program(number, &1))
    |> Enum.reduce_while(%{}, fn text, buckets ->
      crc = Vws.Codecs.CRC16.compute(text)
      bucket = [text | Map.get(buckets, crc, [])]

      if length(bucket) == count,
        do: {:halt, Enum.reverse(bucket)},
        else: {:cont, Map.put(buckets, crc, bucket)}
    end)
  end

  @doc "A program of the same size and CRC-16/ARC as `text`, other bytes (`text` is one of `programs/2`'s form)."
  @spec same_as(binary) :: binary
  def same_as(text) do
    [_, number] = Regex.run(~r/^%\nO(\d+)\n/, text)
    crc = Vws.Codecs.CRC16.compute(text)

    Stream.iterate(0, &(&1 + 1))
    |> Stream.map(&program(String.to_integer(number), &1))
    |> Enum.find(&(&1 != text and Vws.Codecs.CRC16.compute(&1) == crc))
  end

  defp program(number, i) do
    digits = String.pad_leading(Integer.to_string(i), 7, "0")

    "%\nO#{number}\nN10 X" <>
      String.slice(digits, 0, 1) <> "." <> String.slice(digits, 1, 6) <> "\n%\n"
  end
end
