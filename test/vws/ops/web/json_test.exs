defmodule Vws.Ops.Web.JSONTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Ops.Web.JSON

  doctest Vws.Ops.Web.JSON

  # Expected texts from Python 3:
  #   json.dumps(x, ensure_ascii=False, separators=(",", ":"), sort_keys=True)
  describe "golden vectors (Python's json.dumps)" do
    test "an object of the dashboard's kind" do
      assert JSON.encode_to_string(%{partition: "robot", status: "ERROR NO LINK TO VAL II", n: 7}) ==
               ~s({"n":7,"partition":"robot","status":"ERROR NO LINK TO VAL II"})
    end

    test "nested objects and arrays, keys sorted" do
      assert JSON.encode_to_string(%{"b" => [1, -2, nil, false], "a" => %{"z" => "", "y" => 0}}) ==
               ~s({"a":{"y":0,"z":""},"b":[1,-2,null,false]})
    end

    test "escapes" do
      input = "a\b\f\n\r\t\x01\x1f\x7f\"\\/ é→😀"
      expected = ~S("a\b\f\n\r\t\u0001\u001f) <> "\x7f" <> ~S(\"\\/ é→😀")
      assert JSON.encode_to_string(input) == expected
    end

    test "floats, empty containers, atoms" do
      assert JSON.encode_to_string([1.5, -0.5, [], %{}, :executing]) ==
               ~s([1.5,-0.5,[],{},"executing"])
    end
  end

  test "U+2028 and U+2029 are escaped (safe inside a script element)" do
    assert JSON.encode_to_string("a\u2028b\u2029") == ~S("a\u2028b\u2029")
  end

  test "bytes that are not UTF-8 become Latin-1 characters, never an error" do
    assert JSON.encode_to_string(<<"R", 0xFF, 0x81>>) == ~S("R\u00ff\u0081")
  end

  test "terms JSON cannot hold raise ArgumentError" do
    assert_raise ArgumentError, fn -> JSON.encode({:a, 1}) end
    assert_raise ArgumentError, fn -> JSON.encode(%{{:k} => 1}) end
    assert_raise ArgumentError, fn -> JSON.encode([self()]) end
  end

  describe "properties" do
    test "round trip: decoding the output gives the term back" do
      assert_property(
        :proper.forall(json_gen(), fn term ->
          decode(JSON.encode_to_string(term)) == normalise(term)
        end),
        300
      )
    end

    test "any binary encodes to valid UTF-8 JSON that decodes to its characters" do
      assert_property(
        :proper.forall(:proper_types.binary(), fn bin ->
          out = JSON.encode_to_string(bin)
          String.valid?(out) and decode(out) == latin1_fallback(bin)
        end),
        300
      )
    end
  end

  ## Generators

  # terms nested at most three deep, with at most six elements per container
  defp json_gen, do: json_gen(3)

  defp json_gen(0) do
    :proper_types.oneof([
      :proper_types.exactly(nil),
      :proper_types.boolean(),
      :proper_types.integer(),
      :proper_types.float(),
      utf8_gen()
    ])
  end

  defp json_gen(depth) do
    smaller = :proper_types.lazy(fn -> json_gen(depth - 1) end)

    :proper_types.oneof([
      json_gen(0),
      :proper_types.resize(6, :proper_types.list(smaller)),
      :proper_types.bind(
        :proper_types.resize(6, :proper_types.list(:proper_types.tuple([utf8_gen(), smaller]))),
        fn pairs -> Map.new(pairs) end,
        false
      )
    ])
  end

  defp utf8_gen do
    char =
      :proper_types.oneof([
        :proper_types.range(0, 0x7F),
        :proper_types.range(0x80, 0xD7FF),
        :proper_types.range(0xE000, 0x10FFFF)
      ])

    :proper_types.bind(
      :proper_types.resize(16, :proper_types.list(char)),
      &List.to_string/1,
      false
    )
  end

  defp normalise(f) when is_float(f), do: f
  defp normalise(list) when is_list(list), do: Enum.map(list, &normalise/1)
  defp normalise(map) when is_map(map), do: Map.new(map, fn {k, v} -> {k, normalise(v)} end)
  defp normalise(other), do: other

  # what the encoder promises: UTF-8 characters as they are, any other byte as Latin-1
  defp latin1_fallback(bin), do: decode_mixed(bin, "")

  defp decode_mixed(<<>>, acc), do: acc
  defp decode_mixed(<<c::utf8, rest::binary>>, acc), do: decode_mixed(rest, acc <> <<c::utf8>>)
  defp decode_mixed(<<c, rest::binary>>, acc), do: decode_mixed(rest, acc <> <<c::utf8>>)

  defp decode(text), do: Vws.Test.JSONDecode.decode(text)
end
