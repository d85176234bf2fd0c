defmodule Vws.Links.DDCMP.FrameTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.DDCMP.{Error, Frame}
  alias Vws.Links.DDCMP.Frame.{Control, Data, Maintenance}

  doctest Frame

  # Every expected byte string below was computed with python3 (a separate CRC-16/ARC written from
  # the polynomial, checked against "123456789" -> 0xBB3D), never with the code under test.
  @golden [
    {"STRT", &Frame.strt/0, [], "05 06 c0 00 00 01 75 95"},
    {"STACK", &Frame.stack/0, [], "05 07 c0 00 00 01 48 55"},
    {"ACK(R=0)", &Frame.ack/1, [0], "05 01 00 00 00 01 fc 55"},
    {"ACK(R=1)", &Frame.ack/1, [1], "05 01 00 01 00 01 ad 95"},
    {"NAK(3, R=1)", &Frame.nak/2, [3, 1], "05 02 03 01 00 01 e9 d1"},
    {"NAK(:rep_response, R=1)", &Frame.nak/2, [:rep_response, 1], "05 02 03 01 00 01 e9 d1"},
    {"REP(N=1)", &Frame.rep/1, [1], "05 03 00 00 01 01 84 05"},
    {"DATA(N=1, R=0, WHERE)", &Frame.data/3, [1, 0, "\x02\x01\x00WHERE"],
     "81 08 00 00 01 01 3f 80 02 01 00 57 48 45 52 45 1e 33"},
    {"DATA(N=0, R=255, empty)", &Frame.data/3, [0, 255, ""], "81 00 00 ff 00 01 ef e1 00 00"}
  ]

  defp hex(string), do: string |> String.replace(" ", "") |> Base.decode16!(case: :lower)

  defp bin(frame, opts \\ []), do: frame |> Frame.encode(opts) |> IO.iodata_to_binary()

  defp decode_all(bytes, opts \\ []) do
    {items, decoder} = Frame.feed(Frame.new(opts), bytes)
    {items, Frame.buffered_bytes(decoder)}
  end

  describe "golden vectors (PROTOCOLS.md §3)" do
    for {name, constructor, args, wire} <- @golden do
      @constructor constructor
      @args args
      @wire wire
      test "#{name} encodes and decodes" do
        frame = apply(@constructor, @args)
        wire = hex(@wire)
        assert bin(frame, fill: false) == wire
        assert bin(frame) == wire <> <<0xFF>>
        assert decode_all(wire) == {[frame], 0}
        assert decode_all(wire <> <<0xFF>>) == {[frame], 0}
      end
    end

    test "a data message with COUNT > 255 and both flags" do
      data = for i <- 0..299, into: <<>>, do: <<rem(i, 256)>>
      frame = %Data{num: 5, resp: 4, qsync: true, select: true, data: data}
      wire = hex("81 2c c1 04 05 01 31 7a") <> data <> hex("f8 c4")
      assert bin(frame, fill: false) == wire
      assert decode_all(wire) == {[frame], 0}
    end

    test "a maintenance message" do
      frame = %Maintenance{data: "AB"}
      wire = hex("90 02 c0 00 00 01 99 50 41 42 b0 61")
      assert bin(frame, fill: false) == wire
      assert decode_all(wire) == {[frame], 0}
    end

    test "STRT decodes with its flags and zero fields" do
      assert {[%Control{type: :strt, qsync: true, select: true, subtype: 0, addr: 1}], 0} =
               decode_all(hex("96 96 05 06 c0 00 00 01 75 95 ff"))
    end
  end

  describe "NAK reasons" do
    test "names and codes map both ways" do
      pairs = [
        header_crc: 1,
        data_crc: 2,
        rep_response: 3,
        no_buffer: 8,
        overrun: 9,
        too_long: 16,
        header_format: 17
      ]

      for {name, code} <- pairs do
        assert Frame.nak_code(name) == code
        assert Frame.nak_reason(code) == name
        assert Frame.nak(name, 7) == Frame.nak(code, 7)
      end

      assert Frame.nak_reason(4) == 4
      assert Frame.nak_code(4) == 4
      assert_raise ArgumentError, fn -> Frame.nak_code(:bogus) end
      assert_raise ArgumentError, fn -> Frame.nak_code(64) end
    end
  end

  describe "encode errors are programmer errors" do
    test "COUNT above 16383 raises; 16383 encodes" do
      assert_raise ArgumentError, fn ->
        Frame.encode(Frame.data(0, 0, :binary.copy("x", 16384)))
      end

      assert [_ | _] = Frame.encode(Frame.data(0, 0, :binary.copy("x", 16383)))
    end

    test "fields out of range raise" do
      assert_raise ArgumentError, fn -> Frame.encode(%Data{num: 256}) end
      assert_raise ArgumentError, fn -> Frame.encode(%Control{type: :nak, subtype: 64}) end
      assert_raise ArgumentError, fn -> Frame.encode(%Control{type: :bogus}) end
      assert_raise FunctionClauseError, fn -> Frame.ack(-1) end
    end

    test "max_data is checked" do
      assert_raise ArgumentError, fn -> Frame.new(max_data: 16384) end
      assert_raise ArgumentError, fn -> Frame.new(max_data: -1) end
    end
  end

  describe "receive errors are values" do
    test "bad data CRC reports the header's fields" do
      wire = hex("81 08 00 00 01 01 3f 80 02 01 00 57 48 45 52 45 1e 34")

      assert decode_all(wire) ==
               {[{:error, %Error{reason: :data_crc, num: 1, resp: 0, count: 8}}], 0}
    end

    test "a too-long message is reported and skipped without buffering, even across feeds" do
      where = hex("81 08 00 00 01 01 3f 80 02 01 00 57 48 45 52 45 1e 33")
      ack = hex("05 01 00 01 00 01 ad 95")
      error = %Error{reason: :too_long, num: 1, resp: 0, count: 8, max: 4}
      assert decode_all(where <> ack, max_data: 4) == {[{:error, error}, Frame.ack(1)], 0}

      <<head::binary-size(10), tail::binary>> = where
      {[{:error, ^error}], decoder} = Frame.feed(Frame.new(max_data: 4), head)
      assert Frame.buffered_bytes(decoder) == 0
      assert {[%Control{type: :ack, rcvr: 1}], _} = Frame.feed(decoder, [tail, ack])
    end

    test "a good header of unknown control TYPE is a header format error" do
      assert {[{:error, %Error{reason: :header_format, header: <<5, 4, 0, 0, 0, 1>>}}], 0} =
               decode_all(hex("05 04 00 00 00 01 30 55"))
    end

    test "a maintenance header with non-zero fill is a header format error" do
      assert {[{:error, %Error{reason: :header_format}}], 0} =
               decode_all(hex("90 00 c0 01 00 01 b1 50"))
    end

    test "one header CRC error per resync episode" do
      ack = hex("05 01 00 00 00 01 fc 55")
      noise = hex("81 00 00 00 00 00 00 00 05 05 90 00 00 00 00 00 00 00 00")
      err = {:error, %Error{reason: :header_crc}}

      assert decode_all(noise <> ack <> noise <> ack) ==
               {[err, Frame.ack(0), err, Frame.ack(0)], 0}
    end

    test "a frame starting inside a rejected header candidate is found (drop one byte)" do
      # 81 05 01 00 00 00 checks to d3 ed, not 01 fc; the ACK behind the 81 must survive.
      assert decode_all(hex("81 05 01 00 00 00 01 fc 55")) ==
               {[{:error, %Error{reason: :header_crc}}, Frame.ack(0)], 0}
    end

    test "error messages are plain words" do
      for reason <- [:header_crc, :data_crc, :too_long, :header_format] do
        assert Exception.message(%Error{reason: reason, num: 1, count: 9, max: 4}) =~ "DDCMP"
      end
    end
  end

  # Generators ---------------------------------------------------------------------------------

  defp byte, do: :proper_types.integer(0, 255)

  defp sized_binary(max) do
    :proper_types.bind(:proper_types.integer(0, max), &:proper_types.binary/1, false)
  end

  defp data_frame do
    gen =
      :proper_types.tuple([
        byte(),
        byte(),
        byte(),
        :proper_types.boolean(),
        :proper_types.boolean(),
        sized_binary(300)
      ])

    :proper_types.bind(
      gen,
      fn {resp, num, addr, qsync, select, data} ->
        %Data{resp: resp, num: num, addr: addr, qsync: qsync, select: select, data: data}
      end,
      false
    )
  end

  defp control_frame do
    gen =
      :proper_types.tuple([
        :proper_types.elements([:ack, :nak, :rep, :strt, :stack]),
        :proper_types.integer(0, 63),
        byte(),
        byte(),
        byte(),
        :proper_types.boolean(),
        :proper_types.boolean()
      ])

    :proper_types.bind(
      gen,
      fn {type, subtype, rcvr, sndr, addr, qsync, select} ->
        %Control{
          type: type,
          subtype: subtype,
          rcvr: rcvr,
          sndr: sndr,
          addr: addr,
          qsync: qsync,
          select: select
        }
      end,
      false
    )
  end

  defp maintenance_frame do
    gen = :proper_types.tuple([byte(), :proper_types.boolean(), sized_binary(40)])

    :proper_types.bind(
      gen,
      fn {addr, flag, data} ->
        %Maintenance{addr: addr, qsync: flag, select: not flag, data: data}
      end,
      false
    )
  end

  defp any_frame do
    :proper_types.frequency([{3, data_frame()}, {4, control_frame()}, {1, maintenance_frame()}])
  end

  defp fill, do: :proper_types.list(:proper_types.elements([0x96, 0xFF]))

  # Cuts `bytes` at the given points (taken modulo the length) and feeds the pieces one by one.
  defp feed_in_pieces(decoder, bytes, cuts) do
    size = byte_size(bytes)
    points = cuts |> Enum.map(&rem(&1, size + 1)) |> Enum.concat([0, size]) |> Enum.sort()

    points
    |> Enum.chunk_every(2, 1, :discard)
    |> Enum.reduce({[], decoder}, fn [from, to], {acc, decoder} ->
      {items, decoder} = Frame.feed(decoder, binary_part(bytes, from, to - from))
      {acc ++ items, decoder}
    end)
  end

  defp cuts, do: :proper_types.list(:proper_types.integer(0, 100_000))

  # Properties ---------------------------------------------------------------------------------

  test "round trip: every message decodes to itself" do
    prop =
      :proper.forall(any_frame(), fn frame ->
        decode_all(bin(frame)) == {[frame], 0} and
          decode_all(bin(frame, fill: false)) == {[frame], 0}
      end)

    assert_property(prop, 300)
  end

  test "split anywhere with random fill between messages: same messages, empty buffer" do
    gen =
      :proper_types.tuple([:proper_types.list(:proper_types.tuple([fill(), any_frame()])), cuts()])

    prop =
      :proper.forall(gen, fn {filled_frames, cuts} ->
        bytes =
          IO.iodata_to_binary(for {fill, frame} <- filled_frames, do: [fill, Frame.encode(frame)])

        {items, decoder} = feed_in_pieces(Frame.new(), bytes, cuts)
        items == Enum.map(filled_frames, &elem(&1, 1)) and Frame.buffered_bytes(decoder) == 0
      end)

    assert_property(prop, 100)
  end

  test "random bytes never crash, never yield a message that was not on the wire, stay bounded" do
    max_data = 64
    bound = 8 + max_data + 2
    # Random bytes mixed with pieces of real messages, so that good headers and frames occur.
    chunk =
      :proper_types.frequency([
        {3, :proper_types.binary()},
        {2, :proper_types.bind(any_frame(), &bin/1, false)},
        {1,
         :proper_types.bind(
           :proper_types.tuple([any_frame(), :proper_types.integer(0, 400)]),
           fn {frame, n} ->
             frame_bytes = bin(frame)
             binary_part(frame_bytes, 0, rem(n, byte_size(frame_bytes)))
           end,
           false
         )}
      ])

    gen = :proper_types.tuple([:proper_types.list(chunk), cuts()])

    prop =
      :proper.forall(gen, fn {chunks, cuts} ->
        bytes = IO.iodata_to_binary(chunks)
        {items, decoder} = feed_in_pieces(Frame.new(max_data: max_data), bytes, cuts)

        Frame.buffered_bytes(decoder) < bound and
          Enum.all?(items, fn
            {:error, %Error{}} -> true
            frame -> :binary.match(bytes, bin(frame, fill: false)) != :nomatch
          end)
      end)

    assert_property(prop, 200)
  end

  test "a message with any single byte changed is never accepted as that message" do
    gen =
      :proper_types.tuple([
        any_frame(),
        :proper_types.integer(0, 100_000),
        :proper_types.integer(1, 255)
      ])

    prop =
      :proper.forall(gen, fn {frame, at, flip} ->
        wire = bin(frame, fill: false)
        at = rem(at, byte_size(wire))
        <<before::binary-size(at), byte, rest::binary>> = wire
        corrupted = <<before::binary, Bitwise.bxor(byte, flip), rest::binary>>
        {items, _} = decode_all(corrupted <> :binary.copy(<<0xFF>>, 400))
        frame not in items
      end)

    assert_property(prop, 300)
  end

  test "resync: a valid message after garbage is found" do
    no_false_header = fn {garbage, frame} ->
      bytes = garbage <> bin(frame)

      Enum.all?(0..(byte_size(garbage) - 1)//1, fn i ->
        :binary.at(bytes, i) not in [0x81, 0x05, 0x90] or
          Vws.Codecs.CRC16.compute(binary_part(bytes, i, 8)) != 0
      end)
    end

    gen =
      :proper_types.add_constraint(
        :proper_types.tuple([sized_binary(200), any_frame()]),
        no_false_header,
        false
      )

    prop =
      :proper.forall(:proper_types.tuple([gen, cuts()]), fn {{garbage, frame}, cuts} ->
        {items, decoder} = feed_in_pieces(Frame.new(), garbage <> bin(frame), cuts)

        items in [[frame], [{:error, %Error{reason: :header_crc}}, frame]] and
          Frame.buffered_bytes(decoder) == 0
      end)

    assert_property(prop, 200)
  end
end
