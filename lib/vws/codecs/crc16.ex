defmodule Vws.Codecs.CRC16 do
  @moduledoc """
  CRC-16/ARC, the block check of DDCMP (PROTOCOLS.md §3) and of the GE-2000's `C` blocks (§2).

  Polynomial 0x8005 reflected (0xA001), initial value 0, no final XOR. On the wire the CRC is sent
  low byte first, so a block followed by its own CRC checks to 0.

      iex> Vws.Codecs.CRC16.compute("123456789")
      0xBB3D
      iex> Vws.Codecs.CRC16.encode(0xBB3D)
      <<0x3D, 0xBB>>
      iex> Vws.Codecs.CRC16.compute(["123456789", Vws.Codecs.CRC16.encode(0xBB3D)])
      0
  """

  import Bitwise

  @table (for byte <- 0..255 do
            Enum.reduce(1..8, byte, fn _, crc ->
              if band(crc, 1) == 1, do: bxor(crc >>> 1, 0xA001), else: crc >>> 1
            end)
          end)
         |> List.to_tuple()

  @doc "The CRC-16/ARC of `data`, continuing from `crc` (0 to start)."
  @spec compute(iodata, 0..0xFFFF) :: 0..0xFFFF
  def compute(data, crc \\ 0)
  def compute(data, crc) when is_binary(data), do: do_compute(data, crc)
  def compute(data, crc), do: do_compute(IO.iodata_to_binary(data), crc)

  defp do_compute(<<byte, rest::binary>>, crc) do
    do_compute(rest, bxor(crc >>> 8, elem(@table, band(bxor(crc, byte), 0xFF))))
  end

  defp do_compute(<<>>, crc), do: crc

  @doc "The two bytes of a CRC as sent on the wire, low byte first."
  @spec encode(0..0xFFFF) :: <<_::16>>
  def encode(crc), do: <<crc::little-16>>
end
