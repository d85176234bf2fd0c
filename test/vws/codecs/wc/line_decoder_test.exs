defmodule Vws.Codecs.WC.LineDecoderTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.{Error, Generators, LineDecoder}

  doctest LineDecoder

  defp feed(dec, bytes), do: LineDecoder.feed(dec, bytes)

  test "splits on LF and strips one CR" do
    assert {["a", "b", "", "c\r", "d"], dec} = feed(LineDecoder.new(), "a\r\nb\n\r\nc\r\r\nd\ne")
    assert LineDecoder.buffered(dec) == 1
    assert {["e"], dec} = feed(dec, "\n")
    assert LineDecoder.buffered(dec) == 0
  end

  test "a CR split from its LF still ends the line" do
    {[], dec} = feed(LineDecoder.new(), "E\r")
    assert {["E"], _} = feed(dec, "\n")
  end

  test "a line of exactly max_line bytes passes, CR LF not counted" do
    {[], dec} = feed(LineDecoder.new(max_line: 4), "abcd\r")
    assert LineDecoder.buffered(dec) == 5
    assert {["abcd"], _} = feed(dec, "\n")
  end

  test "an overlong line yields one error at once, before its LF, then decoding goes on" do
    dec = LineDecoder.new(max_line: 4)
    # max_line bytes and a CR may still be a good line
    {[], dec} = feed(dec, "abcd\r")
    assert {[{:error, error}], dec} = feed(dec, "e")
    assert %Error{reason: :line_too_long, data: %{length: 6, max_line: 4}} = error
    assert LineDecoder.buffered(dec) == 0
    {[], dec} = feed(dec, String.duplicate("x", 5000))
    {[], dec} = feed(dec, "\r")
    assert {["ok"], dec} = feed(dec, "\nok\n")
    assert LineDecoder.buffered(dec) == 0
  end

  test "an overlong line inside one chunk is reported the same way" do
    assert {["a", {:error, %Error{data: %{length: 5}}}, "b"], _} =
             feed(LineDecoder.new(max_line: 4), "a\nabcde\r\nb\n")
  end

  test "the default limit is 1024 bytes" do
    line = String.duplicate("x", 1024)
    assert {[^line], _} = feed(LineDecoder.new(), line <> "\r\n")

    assert {[{:error, %Error{data: %{length: 1025, max_line: 1024}}}], _} =
             feed(LineDecoder.new(), "x" <> line <> "\r\n")
  end

  test "split anywhere: same lines and errors, bounded buffer, empty at the end" do
    max_line = 16

    content =
      :proper_types.list(
        :proper_types.union([
          :proper_types.range(0, 9),
          :proper_types.range(11, 12),
          :proper_types.range(14, 255)
        ])
      )

    line =
      :proper_types.tuple([
        :proper_types.resize(30, content),
        :proper_types.elements(["\n", "\r\n"])
      ])

    property =
      :proper.forall(
        :proper_types.tuple([:proper_types.list(line), Generators.cuts()]),
        fn {lines, cuts} ->
          bytes = IO.iodata_to_binary(Enum.map(lines, fn {chars, term} -> [chars, term] end))

          expected =
            for {chars, _} <- lines do
              if length(chars) > max_line,
                do: {:error, :line_too_long},
                else: :erlang.list_to_binary(chars)
            end

          {items, dec} =
            Enum.reduce(
              Generators.chunks(bytes, cuts),
              {[], LineDecoder.new(max_line: max_line)},
              fn chunk, {acc, dec} ->
                {items, dec} = LineDecoder.feed(dec, chunk)
                true = LineDecoder.buffered(dec) <= max_line + 1

                items =
                  Enum.map(items, fn
                    {:error, %Error{reason: r, data: %{length: l, max_line: ^max_line}}}
                    when l > max_line ->
                      {:error, r}

                    line ->
                      line
                  end)

                {acc ++ items, dec}
              end
            )

          items == expected and LineDecoder.buffered(dec) == 0
        end
      )

    assert_property(property, 150)
  end
end
