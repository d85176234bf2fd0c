defmodule Vws.Codecs.WC.BCCTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.BCC

  doctest BCC

  # Computed independently with python3: sum(b) % 256 and functools.reduce(xor, b).
  @golden [
    {"*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*", 241, 115},
    {"*0055*S0039ROBOT_CMD*", 32, 34},
    {"05A0054", 111, 69},
    {"13S00390009DONE", 114, 82},
    {"%", 37, 37},
    {"", 0, 0}
  ]

  test "golden block checks, sum and xor" do
    for {data, sum, xor} <- @golden do
      assert BCC.compute(data) == sum
      assert BCC.compute(data, :sum) == sum
      assert BCC.compute(data, :xor) == xor
      assert BCC.compute(for(<<byte <- data>>, do: <<byte>>), :xor) == xor
    end
  end

  test "encode is three digits with leading zeroes" do
    assert BCC.encode(0) == "000"
    assert BCC.encode(7) == "007"
    assert BCC.encode(32) == "032"
    assert BCC.encode(255) == "255"
    assert_raise FunctionClauseError, fn -> BCC.encode(256) end
  end

  test "decode and valid? accept exactly three digits 000-255" do
    assert BCC.decode("000") == {:ok, 0}
    assert BCC.decode("255") == {:ok, 255}

    for field <- ["256", "999", "25", "0255", " 25", "2a5", "", "-01"],
        do: assert(BCC.decode(field) == :error)

    assert BCC.valid?("05A0054", "111")
    assert BCC.valid?("05A0054", "069", :xor)
    refute BCC.valid?("05A0054", "112", :sum)
    refute BCC.valid?("05A0054", "11", :sum)
  end

  test "every value encodes and decodes" do
    for n <- 0..255, do: assert(BCC.decode(BCC.encode(n)) == {:ok, n})
  end

  test "property: the block checks are the byte-by-byte sum mod 256 and XOR, any length" do
    property =
      :proper.forall(:proper_types.binary(), fn data ->
        bytes = :binary.bin_to_list(data)

        BCC.compute(data, :sum) == rem(Enum.sum(bytes), 256) and
          BCC.compute(data, :xor) == Enum.reduce(bytes, 0, &Bitwise.bxor/2)
      end)

    assert_property(property, 500)
  end

  test "a single changed byte always changes both block checks" do
    property =
      :proper.forall(
        :proper_types.tuple([
          :proper_types.non_empty(:proper_types.binary()),
          :proper_types.nat(),
          :proper_types.range(1, 255)
        ]),
        fn {data, at, delta} ->
          pos = rem(at, byte_size(data))
          <<before::binary-size(pos), byte, rest::binary>> = data
          changed = <<before::binary, rem(byte + delta, 256), rest::binary>>

          BCC.compute(changed, :sum) != BCC.compute(data, :sum) and
            BCC.compute(changed, :xor) != BCC.compute(data, :xor)
        end
      )

    assert_property(property, 200)
  end
end
