defmodule Vws.Codecs.RFC2217Test do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.RFC2217

  doctest RFC2217

  defp decode_all(bytes) do
    {events, _} = RFC2217.decode(RFC2217.decoder(), IO.iodata_to_binary(bytes))
    events
  end

  describe "golden vectors (RFC 2217)" do
    test "the client's settings" do
      assert IO.iodata_to_binary(RFC2217.com_port({:baud, 9600})) ==
               <<255, 250, 44, 1, 0, 0, 0x25, 0x80, 255, 240>>

      assert IO.iodata_to_binary(RFC2217.com_port({:data_size, 7})) ==
               <<255, 250, 44, 2, 7, 255, 240>>

      assert IO.iodata_to_binary(RFC2217.com_port({:parity, :even})) ==
               <<255, 250, 44, 3, 3, 255, 240>>

      assert IO.iodata_to_binary(RFC2217.com_port({:stop_size, 2})) ==
               <<255, 250, 44, 4, 2, 255, 240>>

      assert IO.iodata_to_binary(RFC2217.com_port({:control, :xonxoff})) ==
               <<255, 250, 44, 5, 2, 255, 240>>

      assert IO.iodata_to_binary(RFC2217.com_port({:control, :rtscts})) ==
               <<255, 250, 44, 5, 3, 255, 240>>

      assert RFC2217.option(:will, 44) == <<255, 251, 44>>
      assert RFC2217.option(:dont, 0) == <<255, 254, 0>>
    end

    test "a baud rate with a 255 byte is IAC-doubled inside the subnegotiation, and read back" do
      # 65535 = 00 00 FF FF
      wire = IO.iodata_to_binary(RFC2217.com_port({:baud, 65_535}))
      assert wire == <<255, 250, 44, 1, 0, 0, 255, 255, 255, 255, 255, 240>>
      # the server's answer: the same with 101
      answer = :binary.replace(wire, <<44, 1>>, <<44, 101>>)
      assert decode_all(answer) == [{:com_port, {:baud, 65_535}}]
    end

    test "the server's answers and notifications" do
      assert decode_all(<<255, 250, 44, 101, 0, 0, 18, 192, 255, 240>>) ==
               [{:com_port, {:baud, 4800}}]

      assert decode_all(<<255, 250, 44, 102, 8, 255, 240, 255, 250, 44, 104, 1, 255, 240>>) ==
               [{:com_port, {:data_size, 8}}, {:com_port, {:stop_size, 1}}]

      assert decode_all(<<255, 250, 44, 105, 1, 255, 240>>) == [{:com_port, {:control, :none}}]
      assert decode_all(<<255, 250, 44, 106, 0x02, 255, 240>>) == [{:com_port, {:linestate, 2}}]

      assert decode_all(<<255, 250, 44, 107, 0xB0, 255, 240>>) ==
               [{:com_port, {:modemstate, 0xB0}}]

      assert decode_all(<<255, 253, 44, 255, 252, 1, 255, 241, ?x>>) ==
               [{:do, 44}, {:wont, 1}, {:command, 241}, {:data, "x"}]

      assert decode_all(<<255, 250, 24, 0, ?a, 255, 240>>) == [{:subneg, 24, <<0, ?a>>}]

      assert decode_all(<<255, 250, 44, 199, 1, 255, 240>>) == [
               {:com_port, {:unknown, 199, <<1>>}}
             ]
    end

    test "bad subnegotiations are errors, and what follows is read again" do
      long = <<255, 250, 44>> <> :binary.copy("x", 100) <> <<255, 240, ?A>>
      assert decode_all(long) == [{:error, :subneg_too_long}, {:data, "A"}]
      assert decode_all(<<255, 250, 44, 1, 255, 7, ?B>>) == [{:error, :bad_subneg}, {:data, "B"}]
    end
  end

  ## Properties

  defp decode_pieces(pieces) do
    {events, _} =
      Enum.reduce(pieces, {[], RFC2217.decoder()}, fn piece, {acc, d} ->
        {events, d} = RFC2217.decode(d, piece)
        {acc ++ events, d}
      end)

    events
  end

  defp data_of(events), do: for({:data, d} <- events, into: "", do: d)

  test "round trip: any data, IAC included, escaped and split anywhere, comes back as it was" do
    property =
      :proper.forall(
        {:proper_types.binary(), :proper_types.list(:proper_types.non_neg_integer())},
        fn {data, cuts} ->
          # IACs made likely
          data = data <> :binary.copy(<<255>>, rem(byte_size(data), 3))
          wire = IO.iodata_to_binary(RFC2217.escape(data))
          events = decode_pieces(Vws.Test.Serial.split(wire, cuts))
          data_of(events) == data and Enum.all?(events, &match?({:data, _}, &1))
        end
      )

    assert_property(property, 500)
  end

  test "round trip: settings between data, split anywhere" do
    setting =
      :proper_types.oneof([
        :proper_types.bind(:proper_types.integer(0, 0xFFFFFFFF), &{:baud, &1}, false),
        :proper_types.bind(:proper_types.integer(5, 8), &{:data_size, &1}, false),
        :proper_types.bind(
          :proper_types.elements([:none, :odd, :even, :mark, :space]),
          &{:parity, &1},
          false
        ),
        :proper_types.bind(
          :proper_types.elements([1, 2, :one_and_half]),
          &{:stop_size, &1},
          false
        ),
        :proper_types.bind(
          :proper_types.elements([:none, :xonxoff, :rtscts]),
          &{:control, &1},
          false
        )
      ])

    property =
      :proper.forall(
        {:proper_types.list({:proper_types.binary(), setting}),
         :proper_types.list(:proper_types.non_neg_integer())},
        fn {items, cuts} ->
          # as the server sends them: the answer's command is the client's plus 100
          wire =
            IO.iodata_to_binary(
              for {data, s} <- items do
                <<255, 250, 44, c, rest::binary>> = IO.iodata_to_binary(RFC2217.com_port(s))
                [RFC2217.escape(data), <<255, 250, 44, c + 100>>, rest]
              end
            )

          events = decode_pieces(Vws.Test.Serial.split(wire, cuts))

          expected =
            for {data, s} <- items, e <- [{:data, data}, {:com_port, s}], e != {:data, ""}, do: e

          merge(events) == merge(expected)
        end
      )

    assert_property(property, 300)
  end

  defp merge([{:data, a}, {:data, b} | rest]), do: merge([{:data, a <> b} | rest])
  defp merge([e | rest]), do: [e | merge(rest)]
  defp merge([]), do: []

  test "random bytes never crash the decoder, split anywhere" do
    property =
      :proper.forall(
        {:proper_types.list(
           :proper_types.oneof([
             :proper_types.binary(),
             :proper_types.elements([<<255>>, <<255, 250>>, <<255, 240>>, <<255, 250, 44>>])
           ])
         ), :proper_types.list(:proper_types.non_neg_integer())},
        fn {pieces, cuts} ->
          wire = IO.iodata_to_binary(pieces)
          whole = decode_pieces([wire])
          # the same events whole or in pieces (data merged), and each one well formed
          merge(decode_pieces(Vws.Test.Serial.split(wire, cuts))) == merge(whole) and
            Enum.all?(whole, fn
              {:data, d} -> is_binary(d)
              {verb, o} when verb in [:will, :wont, :do, :dont] -> o in 0..255
              {:com_port, _} -> true
              {:subneg, o, p} -> o in 0..255 and byte_size(p) <= 64
              {:command, c} -> c in 0..255
              {:error, r} -> r in [:subneg_too_long, :bad_subneg]
            end)
        end
      )

    assert_property(property, 1000)
  end
end
