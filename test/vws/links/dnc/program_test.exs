defmodule Vws.Links.DNC.ProgramTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.DNC.{Frame, Program}

  doctest Program

  describe "program number" do
    test "the first O word (ISO) or : word (EIA), six digits with leading zeroes" do
      assert Program.number(["%", "O1234", "N10 G00", "O9999"]) == {:ok, "001234"}
      assert Program.number(["%", "N5 :000042", "N10 G00"]) == {:ok, "000042"}
      assert Program.number(["o12"]) == {:ok, "000012"}
      assert Program.number("%\nO123456\n") == {:ok, "123456"}
    end

    test "comments, and O inside other words, are not program numbers" do
      assert Program.number(["(O1234 IS IN A COMMENT)", "N10 GOTO5"]) ==
               {:error, :no_program_number}

      assert Program.number(["N10 (NOTE O77) O78"]) == {:ok, "000078"}
    end

    test "over six digits, and none at all" do
      assert Program.number(["O1234567"]) == {:error, :bad_program_number}
      assert Program.file_name(["N10 G00"]) == {:error, :no_program_number}
      assert Program.file_name(["O7"]) == {:ok, "000007.PRO"}
    end
  end

  test "lines holding CR, LF or a transmission control are found" do
    assert Program.check_lines(["O1", "N10 G00"]) == :ok
    assert Program.check_lines(["O1", "N10\r"]) == {:error, 2}
    assert Program.check_lines([<<"O1", 4>>]) == {:error, 1}
    assert Program.sendable?("N10 G00\nN20 M30\n")
    refute Program.sendable?(<<"N10", 3>>)
  end

  # printable ASCII lines, as the WC link carries them
  defp line, do: :proper_types.list(:proper_types.integer(32, 126))
  defp lines, do: :proper_types.list(line())

  test "lines → DNC text → blocks → text → lines gives the lines back, byte for byte" do
    property =
      :proper.forall({lines(), :proper_types.integer(1, 300)}, fn {lines, max} ->
        lines = Enum.map(lines, &List.to_string/1)
        blocks = Frame.split_text(Program.to_text(lines), max)

        Enum.all?(blocks, &(byte_size(&1) <= max)) and
          Program.from_text(IO.iodata_to_binary(blocks)) == lines
      end)

    assert_property(property, 300)
  end
end
