defmodule Vws.Links.VAL.MessageTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.VAL.{Error, Message}

  doctest Message

  # Expected bytes computed with python3 from PROTOCOLS.md §3 (byte0 LUN, byte1 function,
  # byte2 qualifier, then the text), never with the code under test.
  @golden [
    {"020100444f204d4f56452053414645",
     %Message{lun: 2, function: :write, qualifier: 0, text: "DO MOVE SAFE"}},
    {"0202002e", %Message{lun: 2, function: :read, qualifier: 0, text: "."}},
    {"0301014d4f54494f4e20424547494e",
     %Message{lun: 3, function: :write, qualifier: :motion_begin, text: "MOTION BEGIN"}},
    {"030302", %Message{lun: 3, function: :reply, qualifier: :motion_complete, text: ""}},
    {"02010030", %Message{lun: 2, function: :write, qualifier: 0, text: "0"}},
    {"0201002d363032204c4f434154494f4e204f5554204f46205245414348",
     %Message{lun: 2, function: :write, qualifier: 0, text: "-602 LOCATION OUT OF REACH"}},
    {"010100", %Message{lun: 1, function: :write, qualifier: 0, text: ""}}
  ]

  test "golden vectors encode and decode" do
    for {hex, message} <- @golden do
      bytes = Base.decode16!(hex, case: :lower)
      assert IO.iodata_to_binary(Message.encode(message)) == bytes
      assert Message.decode(bytes) == {:ok, message}
    end
  end

  test "a VAL message inside its DDCMP data message (seed Fig. 11), CRCs from python3" do
    {:ok, m} = Message.new(2, :write, 0, "WHERE")
    frame = Vws.Links.DDCMP.Frame.data(1, 0, Message.encode(m))

    assert IO.iodata_to_binary(Vws.Links.DDCMP.Frame.encode(frame)) ==
             Base.decode16!("8108000001013f8002010057484552451e33ff", case: :lower)
  end

  test "LUN 3 message codes 1-5 decode to names; unknown codes stay numbers" do
    names = [:motion_begin, :motion_complete, :program_start, :program_complete, :error]

    for {name, code} <- Enum.zip(names, 1..5) do
      assert {:ok, %Message{qualifier: ^name}} = Message.decode(<<3, 1, code>>)
      assert {:ok, %Message{qualifier: ^code}} = Message.decode(<<2, 1, code>>)
    end

    assert {:ok, %Message{qualifier: 9}} = Message.decode(<<3, 1, 9>>)
  end

  test "every reason of a refused message" do
    assert {:error, %Error{reason: :too_short}} = Message.decode(<<2, 1>>)
    assert {:error, %Error{reason: :too_short}} = Message.decode(<<>>)
    assert {:error, %Error{reason: :bad_lun, value: 6}} = Message.decode(<<6, 1, 0>>)
    assert {:error, %Error{reason: :bad_function, value: 0}} = Message.decode(<<2, 0, 0>>)
    assert {:error, %Error{reason: :bad_function, value: 4}} = Message.decode(<<2, 4, 0>>)

    assert {:error, %Error{reason: :too_long, value: 257}} =
             Message.decode(<<2, 1, 0>> <> String.duplicate("A", 257))

    assert {:error, %Error{reason: :not_ascii, value: 2}} =
             Message.decode(<<2, 1, 0, "AB", 0xC3>>)

    assert {:error, %Error{reason: :bad_qualifier}} = Message.new(2, :write, :motion_begin, "")
    assert {:error, %Error{reason: :bad_qualifier}} = Message.new(3, :write, 256, "")
    assert {:error, %Error{reason: :bad_function}} = Message.new(2, :ask, 0, "")
    assert {:error, %Error{reason: :bad_lun}} = Message.new(7, :write, 0, "")

    for reason <- [:too_short, :bad_lun, :bad_function, :bad_qualifier, :too_long, :not_ascii] do
      assert Exception.message(%Error{reason: reason, value: 1}) =~ ~r/\w/
    end
  end

  test "256 bytes of text fit; encode refuses what new/4 refuses" do
    text = String.duplicate("Z", 256)
    assert {:ok, m} = Message.new(2, :write, 0, text)
    assert byte_size(IO.iodata_to_binary(Message.encode(m))) == 259

    assert_raise ArgumentError, fn ->
      Message.encode(%Message{lun: 2, function: :write, text: text <> "Z"})
    end
  end

  defp message_gen do
    :proper_types.bind(
      {:proper_types.integer(0, 5), :proper_types.oneof([:write, :read, :reply]),
       :proper_types.integer(0, 255), :proper_types.list(:proper_types.integer(0, 127))},
      fn {lun, function, q, text} ->
        {:ok, m} = Message.new(lun, function, q, :erlang.list_to_binary(Enum.take(text, 256)))
        m
      end,
      false
    )
  end

  test "round trip: decode(encode(m)) == m" do
    assert_property(
      :proper.forall(message_gen(), fn m ->
        Message.decode(IO.iodata_to_binary(Message.encode(m))) == {:ok, m}
      end),
      500
    )
  end

  test "random bytes never crash the decoder, and what it accepts re-encodes to the same bytes" do
    assert_property(
      :proper.forall(:proper_types.binary(), fn bytes ->
        case Message.decode(bytes) do
          {:ok, m} -> IO.iodata_to_binary(Message.encode(m)) == bytes
          {:error, %Error{}} -> true
        end
      end),
      500
    )
  end

  test "a changed header byte never decodes to the same message" do
    assert_property(
      :proper.forall(
        {message_gen(), :proper_types.integer(0, 2), :proper_types.integer(1, 255)},
        fn {m, at, delta} ->
          bytes = IO.iodata_to_binary(Message.encode(m))
          <<pre::binary-size(at), b, post::binary>> = bytes
          flipped = <<pre::binary, rem(b + delta, 256), post::binary>>
          Message.decode(flipped) != {:ok, m}
        end
      ),
      300
    )
  end
end
