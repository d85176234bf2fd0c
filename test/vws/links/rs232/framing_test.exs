defmodule Vws.Links.RS232.FramingTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.RS232.Framing

  doctest Framing

  defp framing(opts) do
    {:ok, f} = Framing.new(opts)
    f
  end

  defp decode_all(f, wire) do
    {events, _} = Framing.decode(Framing.decoder(f), IO.iodata_to_binary(wire))
    events
  end

  @program "%\nO1234\nN10 G01 X1.5 F300\nN20 M30\n%\n"

  describe "golden vectors" do
    test "every end of line, leader and trailer, DC2/DC4" do
      assert IO.iodata_to_binary(Framing.encode(@program, framing(eol: :lf))) ==
               "%\nO1234\nN10 G01 X1.5 F300\nN20 M30\n%\n"

      assert IO.iodata_to_binary(Framing.encode(@program, framing(eol: :cr, leader: 3))) ==
               <<0, 0, 0, "%\rO1234\rN10 G01 X1.5 F300\rN20 M30\r%\r">>

      assert IO.iodata_to_binary(
               Framing.encode(@program, framing(eol: :crlf, dc2_dc4: true, trailer: 2))
             ) == <<0x12, "%\r\nO1234\r\nN10 G01 X1.5 F300\r\nN20 M30\r\n%\r\n", 0x14, 0, 0>>

      # % kept off the wire: DC2/DC4 mark the program, the % lines come back on receive
      f = framing(percent: :strip, dc2_dc4: true, eol: :lf)
      wire = IO.iodata_to_binary(Framing.encode(@program, f))
      assert wire == <<0x12, "O1234\nN10 G01 X1.5 F300\nN20 M30\n", 0x14>>
      assert decode_all(f, wire) == [{:program, @program}]
    end

    test "receiving: leader noise, XON/XOFF, NUL and DEL are not data; any end of line" do
      f = framing([])

      wire =
        "  garbage\r\n" <> <<0, 0x11, 0x7F>> <> "%\nO1234\r\nN10 G01 X1.5 F300\rN20 M30\n%\r\n"

      assert decode_all(f, wire) == [{:program, @program}]
      # a stray XOFF inside the program is flow control, not a character of it
      assert decode_all(f, "%\nO1234\nN10 G01 X1.5" <> <<0x13>> <> " F300\nN20 M30\n%\n") ==
               [{:program, @program}]
    end

    test "a damaged program is an error, never a program" do
      f = framing(dc2_dc4: true)
      assert decode_all(f, "%\nO1\nN1 G0\tX1\n%\n") == [{:error, :bad_character}]
      assert decode_all(f, "%\nO1\nN1 G0 \xC1\n%\n") == [{:error, :bad_character}]
      assert decode_all(f, <<0x12, "%\nO1\nN1", 0x14>>) == [{:error, :incomplete}]

      {events, _} =
        Framing.decode(Framing.decoder(f, max_bytes: 20), "%\nO1\nN10 G01 X1.5 F300\nM30\n%\n")

      assert events == [{:error, :too_long}]
      # and the next program is taken again
      assert decode_all(f, "%\nO1\nN1 G0\tX1\n%\n%\nO2\n%\n") ==
               [{:error, :bad_character}, {:program, "%\nO2\n%\n"}]
    end

    test "bad options are said in words" do
      assert Framing.new(eol: :lfcr) == {:error, "framing: eol is :lf, :cr or :crlf (got :lfcr)"}
      assert {:error, "framing: unknown option :parity" <> _} = Framing.new(parity: :even)

      assert {:error, "framing: percent: :strip needs dc2_dc4: true" <> _} =
               Framing.new(percent: :strip)

      assert {:error, "framing: leader is a count of NUL bytes" <> _} = Framing.new(leader: -1)
    end
  end

  ## Properties

  defp line_gen do
    # printable ASCII, never a line that is "%" alone (that closes a program)
    :proper_types.bind(
      :proper_types.list(:proper_types.integer(0x20, 0x7E)),
      fn chars -> if chars == [?%], do: "%1", else: List.to_string(chars) end,
      false
    )
  end

  defp program_gen do
    :proper_types.bind(
      :proper_types.list(line_gen()),
      fn lines -> Enum.map_join(["%" | lines] ++ ["%"], "", &(&1 <> "\n")) end,
      false
    )
  end

  defp framing_gen do
    :proper_types.bind(
      :proper_types.tuple([
        :proper_types.integer(0, 5),
        :proper_types.integer(0, 5),
        :proper_types.elements([:lf, :cr, :crlf]),
        :proper_types.elements([:keep, :strip]),
        :proper_types.boolean()
      ]),
      fn {leader, trailer, eol, percent, dc} ->
        framing(
          leader: leader,
          trailer: trailer,
          eol: eol,
          percent: percent,
          dc2_dc4: dc or percent == :strip
        )
      end,
      false
    )
  end

  test "round trip: every program in every framing, whole or split anywhere, comes back as it was" do
    property =
      :proper.forall(
        {program_gen(), program_gen(), framing_gen(),
         :proper_types.list(:proper_types.non_neg_integer())},
        fn {p1, p2, f, cuts} ->
          wire = IO.iodata_to_binary([Framing.encode(p1, f), Framing.encode(p2, f)])

          {events, _} =
            Enum.reduce(Vws.Test.Serial.split(wire, cuts), {[], Framing.decoder(f)}, fn piece,
                                                                                        {acc, d} ->
              {events, d} = Framing.decode(d, piece)
              {acc ++ events, d}
            end)

          events == [{:program, p1}, {:program, p2}]
        end
      )

    assert_property(property, 500)
  end

  test "random bytes never crash, and what they make is a whole program or an error" do
    noise =
      :proper_types.list(
        :proper_types.oneof([
          :proper_types.binary(),
          :proper_types.elements(["%", "\r", "\n", "%\n", <<0x12>>, <<0x14>>, "O1\n", <<0x13>>])
        ])
      )

    property =
      :proper.forall({noise, framing_gen()}, fn {pieces, f} ->
        {events, _} =
          Enum.reduce(pieces, {[], Framing.decoder(f, max_bytes: 200)}, fn piece, {acc, d} ->
            {events, d} = Framing.decode(d, piece)
            {acc ++ events, d}
          end)

        Enum.all?(events, fn
          {:program, text} ->
            Vws.Links.DNC.Program.complete?(text) and String.starts_with?(text, "%\n") and
              Vws.Links.DNC.Program.sendable?(text) and byte_size(text) <= 200 + 4

          {:error, reason} ->
            reason in [:bad_character, :incomplete, :too_long]
        end)
      end)

    assert_property(property, 1000)
  end
end
