defmodule Vws.Codecs.WC.ReplyTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.{Error, Generators, LineDecoder, Reply}

  doctest Reply

  # Seed Table 1 replies (the seed prints the status replies without their NN) and NC lines; BCCs
  # over the bytes before them, computed independently with python3: {sum, xor}.
  @golden [
    {{:ack, 54}, "05A0054", "111", "069"},
    {{:status, 39, "0009DONE"}, "13S00390009DONE", "114", "082"},
    {{:status, 40, "0004DONE"}, "13S00400004DONE", "101", "081"},
    {{:ack, 57}, "05A0057", "114", "070"},
    {{:status, 41, "0010DONE"}, "13S00410010DONE", "099", "085"},
    {{:status, 39, ""}, "05S0039", "132", "092"},
    {{:status, 1, String.duplicate("X", 94)}, "99S0001" <> String.duplicate("X", 94), "214",
     "082"}
  ]

  # numbered NC program lines: {number, text, sum, xor}
  @golden_lines [
    {1, "%", "230", "036"},
    {2, "O001234", "059", "073"},
    {45, "G01 X63.5 Y0", "094", "104"},
    {9999, "", "228", "000"}
  ]

  defp wire(reply, opts \\ []), do: IO.iodata_to_binary(Reply.encode(reply, opts))

  test "golden replies, sum and xor" do
    for {reply, body, sum, xor} <- @golden do
      assert wire(reply) == body <> sum <> "\r\n"
      assert wire(reply, bcc: :xor) == body <> xor <> "\r\n"
      assert Reply.decode(body <> sum) == {:ok, reply}
      assert Reply.decode(body <> xor, bcc: :xor) == {:ok, reply}
    end
  end

  test "golden NC program lines, sum and xor" do
    for {n, text, sum, xor} <- @golden_lines do
      body = Vws.Codecs.WC.Command.pad4(n) <> text
      assert wire({:line, n, text}) == body <> sum <> "\r\n"
      assert wire({:line, n, text}, bcc: :xor) == body <> xor <> "\r\n"
      assert Reply.decode_line(body <> sum) == {:ok, {:line, n, text}}
      assert Reply.decode_line(body <> xor, bcc: :xor) == {:ok, {:line, n, text}}
    end
  end

  test "E carries no block check; a line's answer names the line and carries one" do
    assert wire(:nak) == "E\r\n"
    assert wire({:line_ack, 7}) == "A0007008\r\n"
    assert wire({:line_ack, 7}, bcc: :xor) == "A0007070\r\n"
    assert Reply.decode("E") == {:ok, :nak}
    assert Reply.decode("A0007070", bcc: :xor) == {:ok, {:line_ack, 7}}
    # the old one-letter answer is no answer any more: one bit makes A of E
    assert {:error, %Error{}} = Reply.decode("A")
    assert {:error, %Error{reason: :bad_bcc}} = Reply.decode("A0007009")
  end

  test "golden: the answer to a download's closing % names the count and the program's CRC" do
    # PROTOCOLS.md §1 "Whole-program check": A + count + / + CRC-16/ARC (four upper-case hex
    # digits) + BBB; the program ["%", "O001234", "N10 G90 G00 X0 Y0", "N20 M30", "%"] has
    # CRC 52D5 (computed apart from this code base)
    assert wire({:line_ack, 5, 0x52D5}) == "A0005/52D5021\r\n"
    assert wire({:line_ack, 5, 0x52D5}, bcc: :xor) == "A0005/52D5029\r\n"
    assert wire({:line_ack, 0, 0xFFFF}) == "A0000/FFFF072\r\n"
    assert Reply.decode("A0005/52D5021") == {:ok, {:line_ack, 5, 0x52D5}}
    assert Reply.decode("A0005/52D5029", bcc: :xor) == {:ok, {:line_ack, 5, 0x52D5}}
    assert {:error, %Error{reason: :bad_bcc}} = Reply.decode("A0005/52D5022")
    # lower-case hex is not what the CEC sends: damaged
    assert {:error, %Error{}} = Reply.decode("A0005/52d5053")
    assert {:error, %Error{reason: :malformed}} = Reply.decode("A0005-52D5019")
    assert {:error, %Error{}} = Reply.validate({:line_ack, 5, 0x10000})
  end

  test "decode refuses everything else, with a reason" do
    cases = [
      {"", :malformed},
      {"e", :malformed},
      {"EE", :malformed},
      {"05A0054112", :bad_bcc},
      {"05A00541", :malformed},
      {"05A0054111 ", :malformed},
      {"06A0054112", :malformed},
      {"05A00x4178", :bad_sequence},
      {"05Z0054136", :malformed},
      {"13S00390009DON\x01046", :malformed},
      {"%037", :malformed}
    ]

    for {line, reason} <- cases do
      assert {:error, %Error{reason: ^reason}} = Reply.decode(line), inspect(line)
    end
  end

  test "decode_line refuses a bad block check, a missing one and control characters" do
    assert {:error, %Error{reason: :bad_bcc, data: %{computed: 230, received: 231}}} =
             Reply.decode_line("0001%231")

    assert {:error, %Error{reason: :malformed}} = Reply.decode_line("%037")
    assert {:error, %Error{reason: :malformed}} = Reply.decode_line("%")
    assert {:error, %Error{reason: :malformed}} = Reply.decode_line("E")
    assert {:error, %Error{reason: :malformed}} = Reply.decode_line("13S00390009DON\x01046")
  end

  test "a status text over 94 characters is a programmer error; truncate it first" do
    long = String.duplicate("X", 95)

    assert {:error, %Error{reason: :text_too_long, data: %{length: 95, max: 94}}} =
             Reply.validate({:status, 1, long})

    assert_raise ArgumentError, fn -> Reply.encode({:status, 1, long}) end
    assert Reply.truncate_status_text(long) == String.duplicate("X", 94)
    assert Reply.truncate_status_text("DONE") == "DONE"
    assert Reply.validate({:status, 1, Reply.truncate_status_text(long)}) == :ok
  end

  test "encode refuses what could not be sent" do
    for bad <- [
          {:ack, 10_000},
          {:status, -1, "X"},
          {:status, 1, "A\r\nB"},
          {:line, 1, "\t"},
          :line_ack,
          :ok
        ] do
      assert {:error, %Error{}} = Reply.validate(bad)
      assert_raise ArgumentError, fn -> Reply.encode(bad) end
    end
  end

  describe "properties" do
    test "round trip of every reply kind" do
      property =
        :proper.forall(
          :proper_types.tuple([Generators.reply(), Generators.nc_line(), Generators.mode()]),
          fn {reply, line, mode} ->
            decode = fn term, decoder ->
              wire = wire(term, bcc: mode)

              String.ends_with?(wire, "\r\n") and
                decoder.(binary_part(wire, 0, byte_size(wire) - 2), bcc: mode) == {:ok, term}
            end

            decode.(reply, &Reply.decode/2) and decode.(line, &Reply.decode_line/2)
          end
        )

      assert_property(property, 200)
    end

    test "split anywhere through LineDecoder gives the same replies and an empty buffer" do
      property =
        :proper.forall(
          :proper_types.tuple([
            :proper_types.list(Generators.reply()),
            Generators.mode(),
            Generators.cuts()
          ]),
          fn {replies, mode, cuts} ->
            bytes = IO.iodata_to_binary(Enum.map(replies, &Reply.encode(&1, bcc: mode)))
            {lines, dec} = Generators.feed_all(LineDecoder.new(), Generators.chunks(bytes, cuts))

            Enum.map(lines, &Reply.decode(&1, bcc: mode)) == Enum.map(replies, &{:ok, &1}) and
              LineDecoder.buffered(dec) == 0
          end
        )

      assert_property(property, 60)
    end

    test "random bytes never crash the decoders" do
      property =
        :proper.forall(
          :proper_types.tuple([:proper_types.binary(), Generators.mode()]),
          fn {bytes, mode} ->
            Enum.all?([&Reply.decode/2, &Reply.decode_line/2], fn decoder ->
              match?({:ok, _}, decoder.(bytes, bcc: mode)) or
                match?({:error, %Error{}}, decoder.(bytes, bcc: mode))
            end)
          end
        )

      assert_property(property, 300)
    end

    # `E` has no block check (PROTOCOLS.md §1), so only the checked kinds are here.
    test "any single corrupted byte of a checked reply or NC line is rejected" do
      checked =
        :proper_types.union([
          :proper_types.bind(
            :proper_types.range(0, 9999),
            &:proper_types.exactly({:ack, &1}),
            false
          ),
          :proper_types.bind(
            :proper_types.tuple([:proper_types.range(0, 9999), Generators.status_text()]),
            fn {n, text} -> :proper_types.exactly({:status, n, text}) end,
            false
          ),
          Generators.nc_line(),
          :proper_types.bind(
            :proper_types.range(0, 9999),
            &:proper_types.exactly({:line_ack, &1}),
            false
          ),
          :proper_types.bind(
            :proper_types.tuple([:proper_types.range(0, 9999), :proper_types.range(0, 0xFFFF)]),
            fn {n, crc} -> :proper_types.exactly({:line_ack, n, crc}) end,
            false
          )
        ])

      corruption =
        :proper_types.bind(
          :proper_types.tuple([checked, Generators.mode()]),
          fn {reply, mode} ->
            wire = wire(reply, bcc: mode)

            :proper_types.tuple([
              :proper_types.exactly(reply),
              :proper_types.exactly(mode),
              Generators.corruption(binary_part(wire, 0, byte_size(wire) - 2))
            ])
          end,
          false
        )

      property =
        :proper.forall(corruption, fn {reply, mode, {line, pos, index}} ->
          corrupted = Generators.corrupt(line, pos, index)

          decoded =
            case reply do
              {:line, _, _} -> Reply.decode_line(corrupted, bcc: mode)
              _ -> Reply.decode(corrupted, bcc: mode)
            end

          match?({:error, %Error{}}, decoded)
        end)

      assert_property(property, 300)
    end
  end
end
