defmodule Vws.Codecs.WC.ProgramCRCTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.ProgramCRC
  alias Vws.Codecs.CRC16

  doctest ProgramCRC

  # CRC-16/ARC over the program's lines, each ending LF (PROTOCOLS.md §1 "Whole-program
  # check"); the values computed apart from this code base (a bitwise CRC-16/ARC in Python)
  @golden [
    {["%", "O1", "M30", "%"], 0x8B3C, "8B3C"},
    {["%", "O001234", "N10 G90 G00 X0 Y0", "N20 M30", "%"], 0x52D5, "52D5"},
    {["%", "N10 G00X0", "%"], 0xB852, "B852"},
    {["%", "O000777", "N10 G01 X1.0", "%"], 0x084C, "084C"}
  ]

  test "golden programs" do
    for {lines, crc, hex} <- @golden do
      assert ProgramCRC.compute(lines) == crc
      assert ProgramCRC.format(crc) == hex
      assert ProgramCRC.parse(hex) == {:ok, crc}
      assert ProgramCRC.closing_line("%", crc) == "%/" <> hex
    end

    # the CRC of the text, LF included, as the GE-2000's directory gives a file's CRC
    assert ProgramCRC.compute(["12345678"]) == CRC16.compute("12345678\n")
    assert ProgramCRC.format(0) == "0000"
    assert ProgramCRC.format(0xBB3D) == "BB3D"
  end

  test "parse and split_closing refuse what is not four hex digits after a /" do
    for bad <- ["", "123", "12345", "12G4", " 123", "-123"],
        do: assert(ProgramCRC.parse(bad) == :error)

    assert ProgramCRC.parse("bb3d") == {:ok, 0xBB3D}

    for bad <- ["%", "%/123", "%/12G4", "%12345", "/"],
        do: assert(ProgramCRC.split_closing(bad) == :error)

    assert ProgramCRC.split_closing("% /0001") == {:ok, "% ", 1}
    assert ProgramCRC.split_closing("/ABCD") == {:ok, "", 0xABCD}
  end

  defp program,
    do:
      :proper_types.list(
        :proper_types.bind(
          :proper_types.list(:proper_types.range(0x20, 0x7E)),
          &:proper_types.exactly(List.to_string(&1)),
          false
        )
      )

  describe "properties" do
    test "the CRC of the lines is the CRC-16/ARC of the DNC text, kept line by line too" do
      property =
        :proper.forall(program(), fn lines ->
          crc = ProgramCRC.compute(lines)

          crc == CRC16.compute(Vws.Links.DNC.Program.to_text(lines)) and
            crc == Enum.reduce(lines, 0, &ProgramCRC.add_line(&2, &1))
        end)

      assert_property(property, 300)
    end

    test "format, parse and the closing line round trip" do
      property =
        :proper.forall(:proper_types.range(0, 0xFFFF), fn crc ->
          hex = ProgramCRC.format(crc)

          hex =~ ~r/^[0-9A-F]{4}$/ and ProgramCRC.parse(hex) == {:ok, crc} and
            ProgramCRC.split_closing(ProgramCRC.closing_line("%", crc)) == {:ok, "%", crc}
        end)

      assert_property(property, 300)
    end

    test "random bytes never crash parse or split_closing" do
      property =
        :proper.forall(:proper_types.binary(), fn bytes ->
          parsed =
            case ProgramCRC.parse(bytes) do
              {:ok, crc} -> String.upcase(bytes) == ProgramCRC.format(crc)
              :error -> true
            end

          split =
            case ProgramCRC.split_closing(bytes) do
              {:ok, last, crc} ->
                String.upcase(bytes) == String.upcase(last) <> "/" <> ProgramCRC.format(crc)

              :error ->
                true
            end

          parsed and split
        end)

      assert_property(property, 300)
    end

    test "any one line changed changes the CRC of a program (two-bit errors the BCC lets pass)" do
      # a two-bit change that keeps the 8-bit sum: one bit set in one byte, the same bit cleared
      # in another — exactly what the line's BCC cannot see
      property =
        :proper.forall(
          :proper_types.tuple([
            program(),
            :proper_types.range(0, 1_000_000),
            :proper_types.range(0, 6)
          ]),
          fn {lines, r, bit} ->
            case sum_keeping_flip(lines, r, bit) do
              nil ->
                true

              damaged ->
                sum = fn ls -> Enum.sum(Enum.map(ls, &Enum.sum(:binary.bin_to_list(&1)))) end

                sum.(damaged) == sum.(lines) and damaged != lines and
                  ProgramCRC.compute(damaged) != ProgramCRC.compute(lines)
            end
          end
        )

      assert_property(property, 500)
    end
  end

  # flips bit `bit` of two bytes of one line, one 0→1 and one 1→0 (the line's 8-bit sum
  # unchanged), or nil when the program has no such pair
  defp sum_keeping_flip(lines, r, bit) do
    mask = Bitwise.bsl(1, bit)
    candidates = for {l, i} <- Enum.with_index(lines), byte_size(l) >= 2, do: i

    with [_ | _] <- candidates,
         i = Enum.at(candidates, rem(r, length(candidates))),
         bytes = :binary.bin_to_list(Enum.at(lines, i)),
         ones = for({b, j} <- Enum.with_index(bytes), Bitwise.band(b, mask) != 0, do: j),
         zeros = for({b, j} <- Enum.with_index(bytes), Bitwise.band(b, mask) == 0, do: j),
         [_ | _] <- ones,
         [_ | _] <- zeros do
      a = Enum.at(ones, rem(r, length(ones)))
      b = Enum.at(zeros, rem(div(r, 7), length(zeros)))

      flipped =
        bytes
        |> List.update_at(a, &Bitwise.bxor(&1, mask))
        |> List.update_at(b, &Bitwise.bxor(&1, mask))

      List.replace_at(lines, i, :binary.list_to_bin(flipped))
    else
      _ -> nil
    end
  end
end
