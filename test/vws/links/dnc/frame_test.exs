defmodule Vws.Links.DNC.FrameTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.DNC.{Error, Frame}
  alias Vws.Links.DNC.Frame.{Command, Text}

  doctest Frame

  @tc [0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x10, 0x15, 0x16, 0x17]
  @program "N0010 G00 X1.0 Y2.0\nN0020 M30\n"

  # Golden vectors of seed §3.2.2-3.2.7; the BCCs were computed with an independent python3 script
  # (XOR, and a bitwise CRC-16/ARC), not with this code.
  @golden [
    {%Command{direction: :send, check: :lrc, operation: :part_program},
     <<0x01, 0x53, 0x4E, 0x53, 0x02, 0x03, 0x4F>>},
    {%Command{direction: :send, check: :crc, operation: :part_program},
     <<0x01, 0x53, 0x43, 0x53, 0x02, 0x03, 0x20, 0xF8>>},
    {%Command{direction: :send, check: :lrc, operation: :remote_control, text: "000123.PRO"},
     <<0x01, 0x53, 0x4E, 0x4B, 0x02, 0x30, 0x30, 0x30, 0x31, 0x32, 0x33, 0x2E, 0x50, 0x52, 0x4F,
       0x03, 0x34>>},
    {%Command{direction: :send, check: :crc, operation: :remote_control, text: "000123.PRO"},
     <<0x01, 0x53, 0x43, 0x4B, 0x02, 0x30, 0x30, 0x30, 0x31, 0x32, 0x33, 0x2E, 0x50, 0x52, 0x4F,
       0x03, 0x1F, 0xF2>>},
    {%Command{direction: :receive, check: :lrc, operation: :table, text: "TOFFSET"},
     <<0x01, 0x52, 0x4E, 0x4F, 0x02, 0x54, 0x4F, 0x46, 0x46, 0x53, 0x45, 0x54, 0x03, 0x0B>>},
    {%Command{direction: :receive, check: :crc, operation: :table, text: "TOFFSET"},
     <<0x01, 0x52, 0x43, 0x4F, 0x02, 0x54, 0x4F, 0x46, 0x46, 0x53, 0x45, 0x54, 0x03, 0x0B, 0x34>>},
    {%Command{direction: :receive, check: :lrc, operation: :status},
     <<0x01, 0x52, 0x4E, 0x4C, 0x02, 0x03, 0x51>>},
    {%Command{direction: :receive, check: :lrc, operation: :part_program},
     <<0x01, 0x52, 0x4E, 0x53, 0x02, 0x03, 0x4E>>},
    {%Command{direction: :send, check: :lrc, operation: :delete, text: "000123"},
     <<0x01, 0x53, 0x4E, 0x44, 0x02, 0x30, 0x30, 0x30, 0x31, 0x32, 0x33, 0x03, 0x58>>}
  ]

  @golden_text [
    {:lrc, %Text{text: @program},
     <<0x02, 0x4E, 0x30, 0x30, 0x31, 0x30, 0x20, 0x47, 0x30, 0x30, 0x20, 0x58, 0x31, 0x2E, 0x30,
       0x20, 0x59, 0x32, 0x2E, 0x30, 0x0A, 0x4E, 0x30, 0x30, 0x32, 0x30, 0x20, 0x4D, 0x33, 0x30,
       0x0A, 0x03, 0x0B>>},
    {:crc, %Text{text: @program},
     <<0x02, 0x4E, 0x30, 0x30, 0x31, 0x30, 0x20, 0x47, 0x30, 0x30, 0x20, 0x58, 0x31, 0x2E, 0x30,
       0x20, 0x59, 0x32, 0x2E, 0x30, 0x0A, 0x4E, 0x30, 0x30, 0x32, 0x30, 0x20, 0x4D, 0x33, 0x30,
       0x0A, 0x03, 0xC1, 0xF5>>},
    {:lrc, %Text{text: ""}, <<0x02, 0x03, 0x03>>},
    {:crc, %Text{text: ""}, <<0x02, 0x03, 0x40, 0x01>>}
  ]

  @golden_controls [
    {:enq, <<0x05>>},
    {:ack0, <<0x10, 0x30>>},
    {:ack1, <<0x10, 0x31>>},
    {:wack, <<0x10, 0x3B>>},
    {:nak, <<0x15>>},
    {:eot, <<0x04>>}
  ]

  defp bin(iodata), do: IO.iodata_to_binary(iodata)

  defp malformed(byte), do: {:error, %Error{reason: :malformed, byte: byte}}

  defp decode_bytewise(bytes, opts \\ []) do
    {out, decoder} =
      for byte <- :binary.bin_to_list(bytes), reduce: {[], Frame.new(opts)} do
        {out, decoder} ->
          {more, decoder} = Frame.feed(decoder, <<byte>>)
          {out ++ more, decoder}
      end

    assert decoder.buffer == ""
    out
  end

  defp decode(bytes, opts \\ []) do
    {out, decoder} = Frame.feed(Frame.new(opts), bytes)
    {out, decoder.buffer}
  end

  describe "golden vectors" do
    test "command blocks encode and decode byte for byte" do
      for {command, wire} <- @golden do
        assert bin(Frame.encode(command)) == wire
        assert decode(wire) == {[command], ""}
      end
    end

    test "text blocks encode and decode in the check mode of their command" do
      for {check, text, wire} <- @golden_text do
        assert bin(Frame.encode(text, check: check)) == wire
        assert decode(wire, check: check) == {[text], ""}
      end
    end

    test "control sequences, and DEL padding as the GE-2000 sends it" do
      for {control, wire} <- @golden_controls do
        assert bin(Frame.encode(control)) == wire
        assert bin(Frame.encode(control, pad: true)) == wire <> <<0x7F>>
        assert decode(wire) == {[control], ""}
      end

      assert decode(<<0x05, 0x7F>>) == {[:enq], ""}
      assert decode(<<0x04, 0x7F>>) == {[:eot], ""}
      assert decode(<<0x10, 0x7F, 0x30>>) == {[:ack0], ""}
      assert decode(<<0x7F, 0x7F>>) == {[], ""}
    end

    test "the seed's upload dialogue (§3.2.3) as the CEC receives it" do
      # CEC sent SOH RCS ..., so it sets CRC itself; the GE's EOT DEL ends the upload.
      [_, crc_block, _, _] = @golden_text

      bytes =
        <<0x10, 0x30, 0x10, 0x31, 0x05, 0x7F>> <>
          elem(crc_block, 2) <>
          elem(crc_block, 2) <>
          <<0x04, 0x7F>>

      {out, decoder} = Frame.feed(Frame.set_check(Frame.new(), :crc), bytes)
      assert out == [:ack0, :ack1, :enq, %Text{text: @program}, %Text{text: @program}, :eot]
      assert Frame.check(decoder) == :lrc
      assert decoder.buffer == ""
    end
  end

  describe "check mode" do
    test "a command switches the mode for the text blocks after it; EOT resets it" do
      scs = %Command{check: :crc, operation: :part_program}
      text = %Text{text: "N1\n"}

      bytes =
        bin([
          Frame.encode(scs),
          Frame.encode(text, check: :crc),
          Frame.encode(:eot),
          Frame.encode(text, check: :lrc)
        ])

      assert decode(bytes) == {[scs, text, :eot, text], ""}
    end

    test "after an R command the mode survives the turnaround EOT, and the next EOT resets it" do
      rcs = %Command{direction: :receive, check: :crc, operation: :part_program}
      text = %Text{text: "N1\n"}

      bytes =
        bin([
          Frame.encode(rcs),
          Frame.encode(:eot),
          Frame.encode(:enq, pad: true),
          Frame.encode(text, check: :crc),
          Frame.encode(:eot, pad: true),
          Frame.encode(text, check: :lrc)
        ])

      assert decode(bytes) == {[rcs, :eot, :enq, text, :eot, text], ""}
    end

    test "set_check/2 and new(check: ...)" do
      assert Frame.check(Frame.new()) == :lrc
      assert Frame.check(Frame.new(check: :crc)) == :crc
      assert Frame.check(Frame.set_check(Frame.new(), :crc)) == :crc
      assert_raise ArgumentError, fn -> Frame.set_check(Frame.new(), :none) end
    end
  end

  describe "errors" do
    test "a bad BCC is a value, and decoding goes on" do
      bytes = <<0x01, 0x53, 0x4E, 0x53, 0x02, 0x03, 0x4E, 0x05>>

      assert decode(bytes) ==
               {[{:error, %Error{reason: :bad_bcc}}, :enq], ""}
    end

    test "an overlong block is reported once and skipped through its ETX and BCC" do
      long = String.duplicate("A", 20)
      # Its BCC byte happens to be STX: it must not open a block.
      bytes = bin([0x02, long, 0x03, 0x02, Frame.encode(:ack1)])
      assert decode(bytes, max_text: 10) == {[{:error, %Error{reason: :too_long}}, :ack1], ""}

      {out, decoder} =
        for byte <- :binary.bin_to_list(bytes), reduce: {[], Frame.new(max_text: 10)} do
          {out, decoder} ->
            {more, decoder} = Frame.feed(decoder, <<byte>>)
            {out ++ more, decoder}
        end

      assert {out, decoder.buffer} == {[{:error, %Error{reason: :too_long}}, :ack1], ""}
    end

    test "an overlong CRC block is skipped through both CRC bytes, whatever they are" do
      bytes = bin([0x01, "SCS", 0x02, String.duplicate("A", 20), 0x03, 0x05, 0x05, 0x10, ?1])
      assert decode(bytes, max_text: 10) == {[{:error, %Error{reason: :too_long}}, :ack1], ""}
    end

    test "an overlong block cut short by a control resyncs on that control" do
      bytes = bin([0x01, "SNS", 0x02, String.duplicate("A", 20), 0x05])
      assert decode(bytes, max_text: 10) == {[{:error, %Error{reason: :too_long}}, :enq], ""}
    end

    test "a block at max_text is accepted" do
      text = %Text{text: String.duplicate("A", 10)}
      assert decode(bin(Frame.encode(text, max_text: 10)), max_text: 10) == {[text], ""}
    end

    test "a block broken off by EOT is malformed, and the EOT (the sender's abort) is kept" do
      assert decode(<<0x02, "N10", 0x04>>) ==
               {[{:error, %Error{reason: :malformed, byte: 0x04}}, :eot], ""}

      assert decode(<<0x01, "S", 0x04, 0x7F>>) ==
               {[{:error, %Error{reason: :malformed, byte: 0x04}}, :eot], ""}

      assert decode(<<0x01, "SX">>) ==
               {[{:error, %Error{reason: :malformed, byte: ?X}}], ""}

      assert decode(<<0x10, ?2, ?3>>) ==
               {[{:error, %Error{reason: :malformed, byte: ?2}}], ""}

      # ENQ in a block is X3.28's block abort: answered by the NAK the error draws, not decoded
      assert decode(<<0x01, 0x05>>) ==
               {[{:error, %Error{reason: :malformed, byte: 0x05}}], ""}
    end

    # LRCs of the blocks below computed with python3 (XOR of text and ETX).
    @n60 %Text{text: "N60 G01 X6.5\n"}
    @n60_wire <<0x02, "N60 G01 X6.5\n", 0x03, 0x72>>

    test "a block broken off by any other control is one error; its rest goes with it" do
      # seed 6 of the line test: a flipped bit turns the 0 of N60 into DLE
      damaged = <<0x02, "N6", 0x10, " G01 X6.5\n", 0x03, 0x72>>
      assert decode(damaged <> @n60_wire) == {[malformed(0x10), @n60], ""}

      # the same block cut by each control (ENQ: the sender's block abort); the block sent
      # again after the one NAK is taken
      for control <- [0x01, 0x02, 0x05, 0x06, 0x10, 0x15, 0x16, 0x17],
          {head, tail} <- [{"N60", " G01 X6.5\n"}, {"N60 G01 X6.5", ""}, {"", "N60"}] do
        damaged = <<0x02, head::binary, control, tail::binary, 0x03, 0x72>>
        assert decode(damaged <> @n60_wire) == {[malformed(control), @n60], ""}
        # fed byte by byte
        assert decode_bytewise(damaged <> @n60_wire) == [malformed(control), @n60]
      end

      # the drop ends at the sender's next ENQ (its poll when the ETX was lost too)
      assert decode(<<0x02, "N6", 0x10, " G01", 0x05>>) == {[malformed(0x10), :enq], ""}
      # DLE 1 or NAK in the tail are not replies: the tail is the sender's text
      assert decode(<<0x02, "N6", 0x10, "1 ", 0x15, 0x03, 0x72>>) == {[malformed(0x10)], ""}
    end

    test "a damaged command header is one error too: its own STX starts nothing" do
      # RNS 004711.PRO, LRC 0x2E; seed 10 of the line test turned its R (0x52) into 0xD2
      rns = %Command{direction: :receive, operation: :part_program, text: "004711.PRO"}
      good = <<0x01, "RNS", 0x02, "004711.PRO", 0x03, 0x2E>>
      assert decode(good) == {[rns], ""}

      for {at, byte} <- [{1, 0xD2}, {2, 0x03}, {3, 0x7F}, {4, ?X}] do
        <<head::binary-size(at), _, tail::binary>> = good
        damaged = <<head::binary, byte, tail::binary>>
        assert decode(damaged <> good) == {[malformed(byte), rns], ""}
        assert decode_bytewise(damaged <> good) == [malformed(byte), rns]
      end
    end

    test "a block whose STX was damaged is garbage, and its BCC is never decoded, even as EOT" do
      # LRC of "N20 G01 X1.5 T01\n" ETX is 0x04: EOT (seed 6: an upload ended early this way)
      lost_start = <<?B, "N20 G01 X1.5 T01\n", 0x03, 0x04>>
      unexpected = {:error, %Error{reason: :unexpected_byte, byte: ?B}}
      assert decode(lost_start) == {[unexpected], ""}
      # no reply: the sender polls, then sends it again
      again = <<0x02, "N20 G01 X1.5 T01\n", 0x03, 0x04>>

      assert decode(lost_start <> <<0x05>> <> again) ==
               {[unexpected, :enq, %Text{text: "N20 G01 X1.5 T01\n"}], ""}

      # a CRC block's two BCC bytes are skipped, whatever they are
      assert decode(<<0x7F, 0x03, 0x04, 0x05, 0x10, ?1>>, check: :crc) ==
               {[{:error, %Error{reason: :unexpected_byte, byte: 0x03}}, :ack1], ""}
    end

    test "garbage between blocks is one error per run" do
      assert decode(<<"garbage", 0x7F, "more", 0x05, "x", 0x04>>) ==
               {[
                  {:error, %Error{reason: :unexpected_byte, byte: ?g}},
                  :enq,
                  {:error, %Error{reason: :unexpected_byte, byte: ?x}},
                  :eot
                ], ""}
    end

    test "the seed's SOH SOH SOH collapses to one pending SOH" do
      {[], decoder} = Frame.feed(Frame.new(), <<0x01, 0x01, 0x01>>)
      assert decoder.buffer == <<0x01>>
      {out, decoder} = Frame.feed(decoder, <<0x53, 0x4E, 0x53, 0x02, 0x03, 0x4F>>)
      assert out == [%Command{}]
      assert decoder.buffer == ""
    end

    test "messages are plain words" do
      for reason <- [:bad_bcc, :too_long, :malformed, :unexpected_byte] do
        assert Exception.message(%Error{reason: reason, byte: 0x1F}) =~ ~r/\w+ \w+/
      end

      assert Exception.message(%Error{reason: :unexpected_byte, byte: 0x0A}) =~ "0x0A"
    end
  end

  describe "encode refuses" do
    test "transmission controls in text, overlong text, bad fields" do
      for byte <- @tc do
        assert_raise ArgumentError, fn -> Frame.encode(%Text{text: <<"N1", byte>>}) end
        assert_raise ArgumentError, fn -> Frame.encode(%Command{text: <<byte>>}) end
      end

      assert_raise ArgumentError, fn -> Frame.encode(%Text{text: String.duplicate("A", 257)}) end
      assert bin(Frame.encode(%Text{text: String.duplicate("A", 256)})) |> byte_size() == 259
      assert_raise ArgumentError, fn -> Frame.encode(%Text{text: "AB"}, max_text: 1) end
      assert_raise ArgumentError, fn -> Frame.encode(%Command{operation: :fly}) end
      assert_raise ArgumentError, fn -> Frame.encode(%Command{check: :none}) end
      assert_raise ArgumentError, fn -> Frame.encode(%Text{}, check: :none) end
      assert_raise ArgumentError, fn -> Frame.encode(:ack2) end
      # DEL, LF, CR and 8-bit bytes are data.
      text = %Text{text: <<"N1", 0x7F, "\r\n", 0xFF>>}
      assert decode(bin(Frame.encode(text))) == {[text], ""}
    end
  end

  test "every single-byte corruption of a golden block is never accepted as that block" do
    blocks =
      Enum.map(@golden, fn {command, wire} -> {command, :lrc, wire} end) ++
        Enum.map(@golden_text, fn {check, text, wire} -> {text, check, wire} end)

    for {frame, check, wire} <- blocks,
        pos <- 0..(byte_size(wire) - 1),
        <<head::binary-size(pos), original, tail::binary>> = wire,
        byte <- 0..255,
        byte != original do
      {out, _} = decode(<<head::binary, byte, tail::binary>>, check: check)
      refute frame in out, "#{inspect(frame)} accepted with byte #{pos} set to #{byte}"
    end
  end

  ## Properties

  @max 24
  @text_bytes Enum.to_list(0..255) -- @tc

  defp text_gen do
    byte =
      :proper_types.frequency([
        {3, :proper_types.range(0x20, 0x7E)},
        {1, :proper_types.elements([?\n, ?\r, 0x7F])},
        {1, :proper_types.elements(@text_bytes)}
      ])

    :proper_types.bind(
      :proper_types.list(byte),
      fn bytes -> bytes |> Enum.take(@max) |> :binary.list_to_bin() end,
      false
    )
  end

  defp check_gen, do: :proper_types.elements([:lrc, :crc])

  defp command_gen do
    :proper_types.bind(
      :proper_types.tuple([
        :proper_types.elements([:send, :receive]),
        check_gen(),
        :proper_types.elements([
          :part_program,
          :table,
          :remote_control,
          :status,
          :delete,
          :directory,
          :download_execute,
          :binary
        ]),
        text_gen()
      ]),
      fn {dir, check, op, text} ->
        %Command{direction: dir, check: check, operation: op, text: text}
      end,
      false
    )
  end

  defp item_gen do
    :proper_types.frequency([
      {2, :proper_types.elements([:enq, :ack0, :ack1, :wack, :nak, :eot])},
      {2, command_gen()},
      {3, :proper_types.bind(text_gen(), &%Text{text: &1}, false)}
    ])
  end

  # The mode rule of the moduledoc, written independently of the decoder: which check the sender
  # of each text block uses.
  defp encode_stream(items, pads) do
    {wires, _} =
      items
      |> Enum.zip(Stream.cycle(pads))
      |> Enum.map_reduce({:lrc, false}, fn {item, pad}, {check, reverse} ->
        opts = [check: check, pad: pad, max_text: @max]

        state =
          case item do
            %Command{check: c, direction: d} -> {c, d == :receive}
            :eot when reverse -> {check, false}
            :eot -> {:lrc, false}
            _ -> {check, reverse}
          end

        {bin(Frame.encode(item, opts)), state}
      end)

    IO.iodata_to_binary(wires)
  end

  defp feed_pieces(decoder, bytes, cuts) do
    points =
      cuts |> Enum.map(&rem(&1, byte_size(bytes) + 1)) |> Enum.concat([0, byte_size(bytes)])

    points
    |> Enum.sort()
    |> Enum.chunk_every(2, 1, :discard)
    |> Enum.reduce({[], decoder}, fn [from, to], {out, decoder} ->
      {more, decoder} = Frame.feed(decoder, binary_part(bytes, from, to - from))
      {out ++ more, decoder}
    end)
  end

  test "round trip of every kind of frame, both check modes, with and without DEL" do
    prop =
      :proper.forall(
        :proper_types.tuple([item_gen(), check_gen(), :proper_types.boolean()]),
        fn {item, check, pad} ->
          wire = bin(Frame.encode(item, check: check, pad: pad, max_text: @max))
          decode(wire, check: check, max_text: @max) == {[item], ""}
        end
      )

    assert_property(prop, 400)
  end

  test "split anywhere: a mixed stream cut at random points decodes to the same frames" do
    prop =
      :proper.forall(
        :proper_types.tuple([
          :proper_types.list(item_gen()),
          :proper_types.non_empty(:proper_types.list(:proper_types.boolean())),
          :proper_types.list(:proper_types.non_neg_integer())
        ]),
        fn {items, pads, cuts} ->
          bytes = encode_stream(items, pads)
          {out, decoder} = feed_pieces(Frame.new(max_text: @max), bytes, cuts)
          out == items and decoder.buffer == "" and decoder.state == :idle
        end
      )

    assert_property(prop, 200)
  end

  defp noisy_gen do
    byte =
      :proper_types.frequency([
        {4, :proper_types.elements([0x01, 0x02, 0x03, 0x04, 0x05, 0x10, 0x15, 0x7F])},
        {4, :proper_types.elements(~c"SRNCOKLDFEQ01;A\n")},
        {2, :proper_types.range(0, 255)}
      ])

    chunk =
      :proper_types.frequency([
        {3, :proper_types.bind(:proper_types.list(byte), &:binary.list_to_bin/1, false)},
        {1,
         :proper_types.bind(
           :proper_types.tuple([item_gen(), check_gen()]),
           fn {item, check} -> bin(Frame.encode(item, check: check, max_text: @max)) end,
           false
         )}
      ])

    :proper_types.bind(:proper_types.list(chunk), &IO.iodata_to_binary/1, false)
  end

  defp in_input?(%Command{} = c, bytes),
    do: :binary.match(bytes, bin(Frame.encode(c))) != :nomatch

  defp in_input?(%Text{} = t, bytes) do
    Enum.any?([:lrc, :crc], &(:binary.match(bytes, bin(Frame.encode(t, check: &1))) != :nomatch))
  end

  defp in_input?(_control, _bytes), do: true

  test "random bytes never crash, stay bounded and yield only blocks present with a good check" do
    prop =
      :proper.forall(
        :proper_types.tuple([noisy_gen(), :proper_types.list(:proper_types.non_neg_integer())]),
        fn {bytes, cuts} ->
          {out, decoder} = feed_pieces(Frame.new(max_text: @max), bytes, cuts)

          byte_size(decoder.buffer) <= @max + 8 and
            Enum.all?(out, fn
              {:error, %Error{reason: r}} ->
                r in [:bad_bcc, :too_long, :malformed, :unexpected_byte]

              control when is_atom(control) ->
                control in [:enq, :ack0, :ack1, :wack, :nak, :eot]

              frame ->
                in_input?(frame, bytes)
            end)
        end
      )

    assert_property(prop, 300)
  end

  test "a block with any one byte changed is never accepted as that block" do
    block_gen =
      :proper_types.frequency([
        {1, :proper_types.bind(text_gen(), &%Text{text: &1}, false)},
        {1, command_gen()}
      ])

    prop =
      :proper.forall(
        :proper_types.tuple([
          block_gen,
          check_gen(),
          :proper_types.non_neg_integer(),
          :proper_types.range(1, 255)
        ]),
        fn {block, check, pos, delta} ->
          wire = bin(Frame.encode(block, check: check, max_text: @max))
          pos = rem(pos, byte_size(wire))
          <<head::binary-size(pos), original, tail::binary>> = wire
          corrupt = <<head::binary, rem(original + delta, 256), tail::binary>>
          {out, _} = decode(corrupt, check: check, max_text: @max)
          # Followed by more traffic, too: the damaged block must not be completed by it.
          {out2, _} = decode(corrupt <> <<0x04, 0x04, 0x05>>, check: check, max_text: @max)
          block not in out and block not in out2
        end
      )

    assert_property(prop, 500)
  end

  # What the receiving link answers: NAK to these errors, its last reply again to ENQ.
  defp replies(out) do
    Enum.count(out, fn
      {:error, %Error{reason: r}} -> r in [:bad_bcc, :malformed, :too_long]
      control -> control == :enq
    end)
  end

  defp poll_and_resend(out, decoder, wire, polls) do
    if replies(out) > 0 or :eot in out or polls == 0 do
      {more, decoder} = Frame.feed(decoder, wire)
      {out ++ more, decoder}
    else
      {more, decoder} = Frame.feed(decoder, <<0x05>>)
      poll_and_resend(out ++ more, decoder, wire, polls - 1)
    end
  end

  test "one flipped bit in a block draws one reply, and the block sent again is taken once" do
    program = for n <- 1..12, do: %Text{text: "N#{n * 10} G01 X#{n}.5 Y-#{n}.25 F300\n"}

    blocks =
      Enum.map(@golden, fn {command, wire} -> {command, :lrc, wire} end) ++
        Enum.map(@golden_text, fn {check, text, wire} -> {text, check, wire} end) ++
        for text <- program,
            check <- [:lrc, :crc],
            do: {text, check, bin(Frame.encode(text, check: check))}

    for {block, check, wire} <- blocks,
        pos <- 0..(byte_size(wire) - 1),
        bit <- 0..7 do
      <<head::binary-size(pos), original, tail::binary>> = wire
      flipped = Bitwise.bxor(original, Bitwise.bsl(1, bit))

      {first, decoder} =
        Frame.feed(Frame.new(check: check), <<head::binary, flipped, tail::binary>>)

      refute block in first

      # what the sender does next: after a reply it sends the block again; without one it
      # polls with ENQ until it gets one (an empty block's BCC is ETX: when its STX is lost, the
      # skip of that "BCC" takes the first poll), at most 3 times
      {out, decoder} = poll_and_resend(first, decoder, wire, 3)
      taken = Enum.count(out, &(&1 == block))

      cond do
        # a flip into EOT reads as the sender's abort: the transmission ends in error
        :eot in out ->
          assert taken <= 1

        # the two flips that can draw a second reply, which the receiving link must survive (it
        # drops copies): SOH made ENQ, a real-looking poll ahead of a block whose header then
        # goes wrong; and ETX made STX or SOH, where the BCC is read as text and may hold a start
        (pos == 0 and flipped == 0x05) or (original == 0x03 and flipped in [0x01, 0x02]) ->
          assert taken <= 1 and replies(out) <= 2

        true ->
          assert {taken, replies(out), decoder.state, decoder.buffer} == {1, 1, :idle, ""},
                 "bit #{bit} of byte #{pos} of #{inspect(wire)}: #{inspect(out)}"
      end
    end
  end

  test "a decoded block does not keep the chunk it came in alive" do
    text = String.duplicate("N10 G01 X1.5\n", 15)
    command = %Command{text: "000123.PRO"}
    pad = :binary.copy(<<0x7F>>, 1_000_000)
    chunk = bin([Frame.encode(%Text{text: text}), Frame.encode(command), pad, 0x02, "N20"])
    assert byte_size(chunk) > 1_000_000

    {[%Text{text: decoded}, %Command{text: name}], decoder} = Frame.feed(Frame.new(), chunk)
    assert decoded == text and name == command.text
    assert :binary.referenced_byte_size(decoded) == byte_size(decoded)
    assert :binary.referenced_byte_size(name) == byte_size(name)
    # and the unfinished block kept for the next feed
    assert decoder.buffer == <<0x02, "N20">>
    assert :binary.referenced_byte_size(decoder.buffer) == byte_size(decoder.buffer)
  end

  describe "split_text/2" do
    test "cuts at the last LF that fits, and hard-cuts lines that do not fit" do
      assert Frame.split_text("") == []
      assert Frame.split_text("N1\nN2\n", 256) == ["N1\nN2\n"]
      assert Frame.split_text("N1\nN2\nN3\n", 6) == ["N1\nN2\n", "N3\n"]
      assert Frame.split_text("N1\nN2\nN3\n", 7) == ["N1\nN2\n", "N3\n"]
      assert Frame.split_text("ABCDEFG\nH\n", 3) == ["ABC", "DEF", "G\n", "H\n"]
      assert Frame.split_text("ABCD", 2) == ["AB", "CD"]
    end

    test "two equal blocks in a row are cut differently" do
      assert Frame.split_text("G04\nG04\nG04\n", 4) == ["G04\n", "G04", "\n", "G04\n"]
      # (greedy, then shorter, would end "\n", "\n": the end is cut again)
      assert Frame.split_text("\n\n\n\n", 2) == ["\n", "\n\n", "\n"]
      assert Frame.split_text("G04 P1\nG04 P1\nM30\n", 7) == ["G04 P1\n", "G04 P1", "\nM30\n"]
    end

    test "property: nothing lost, every part fits, no two parts in a row equal, else the greedy LF cuts" do
      prop =
        :proper.forall(
          :proper_types.tuple([
            :proper_types.list(:proper_types.elements(~c"AB\n")),
            :proper_types.range(1, 12)
          ]),
          fn {chars, max} ->
            program = :binary.list_to_bin(chars)
            parts = Frame.split_text(program, max)
            greedy = greedy_split(program, max)

            distinct? = fn list ->
              list |> Enum.chunk_every(2, 1, :discard) |> Enum.all?(fn [a, b] -> a != b end)
            end

            (IO.iodata_to_binary(parts) == program and
               Enum.all?(parts, &(byte_size(&1) in 1..max)) and
               (max < 2 or distinct?.(parts)) and
               (not distinct?.(greedy) or parts == greedy)) or
              (IO.inspect({program, max, parts}) && false)
          end
        )

      assert_property(prop, 300)
    end
  end

  # every block ends at the last LF that fits, a line longer than max cut at max
  defp greedy_split(<<>>, _max), do: []

  defp greedy_split(rest, max) when byte_size(rest) <= max, do: [rest]

  defp greedy_split(rest, max) do
    size =
      case :binary.matches(binary_part(rest, 0, max), "\n") do
        [] -> max
        matches -> elem(List.last(matches), 0) + 1
      end

    <<part::binary-size(size), rest::binary>> = rest
    [part | greedy_split(rest, max)]
  end
end
