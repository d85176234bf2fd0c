defmodule Vws.Codecs.WC.CommandStringTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.{Command, CommandString, Error, Generators, LineDecoder}

  doctest CommandString

  # Seed Table 1 ("D0 Move MV1: TRANS" is OCR for DO MOVE MV1:TRANS, PROTOCOLS.md §1). BCCs over
  # the first through the last `*`, computed independently with python3: {sum, xor}.
  @table_1 [
    {"*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*", "241", "115", 54,
     [{"R", :robot, 9, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"}, {"G", :gripper, 4, "OPEN"}]},
    {"*0055*S0039ROBOT_CMD*", "032", "034", 55, [{"S", :status, 39, "ROBOT_CMD"}]},
    {"*0056*S0040GRIPPER_CMD*", "172", "032", 56, [{"S", :status, 40, "GRIPPER_CMD"}]},
    {"*0057*R0010DISABLE_TRAY1*", "033", "095", 57, [{"R", :robot, 10, "DISABLE_TRAY1"}]},
    {"*0058*S0041ROBOT_CMD*", "028", "032", 58, [{"S", :status, 41, "ROBOT_CMD"}]}
  ]

  defp string(seq, commands) do
    %CommandString{
      sequence: seq,
      commands:
        for(
          {letter, set, n, text} <- commands,
          do: %Command{letter: letter, set: set, number: n, text: text}
        )
    }
  end

  defp wire(string, opts \\ []), do: IO.iodata_to_binary(CommandString.encode(string, opts))

  describe "seed Table 1" do
    test "encodes to the golden bytes, sum and xor" do
      for {covered, sum, xor, seq, commands} <- @table_1 do
        assert wire(string(seq, commands)) == covered <> sum <> "\r\n"
        assert wire(string(seq, commands), bcc: :sum) == covered <> sum <> "\r\n"
        assert wire(string(seq, commands), bcc: :xor) == covered <> xor <> "\r\n"
      end
    end

    test "decodes from the golden bytes, sum and xor" do
      for {covered, sum, xor, seq, commands} <- @table_1 do
        assert CommandString.decode(covered <> sum) == {:ok, string(seq, commands)}
        assert CommandString.decode(covered <> xor, bcc: :xor) == {:ok, string(seq, commands)}
      end
    end

    test "the other mode's block check is refused" do
      {covered, sum, xor, _, _} = hd(@table_1)

      assert {:error, %Error{reason: :bad_bcc, data: %{computed: 241, received: 115}}} =
               CommandString.decode(covered <> xor)

      assert {:error, %Error{reason: :bad_bcc, data: %{computed: 115, received: 241}}} =
               CommandString.decode(covered <> sum, bcc: :xor)
    end
  end

  describe "decode is lenient on nothing" do
    # Each input has a valid sum BCC (python3) so that the check named is the one that fails.
    test "every syntax rule has its reason" do
      cases = [
        {"", :malformed},
        {"*0054*R0009X*24", :malformed},
        {"*0054*R0009X*256", :malformed},
        {"*0054*R0009X*1860", :malformed},
        {"*0054*R0009X*186\r", :malformed},
        {"0054*R0009X*186", :malformed},
        {"*0054*R0009X186", :malformed},
        {"*0054*R0009X*187", :bad_bcc},
        {"*0054*029", :malformed},
        {"**084", :malformed},
        {"*054*R0009X*138", :bad_sequence},
        {"*0054*r0009X*218", :bad_command},
        {"*0054*R009X*138", :bad_command},
        {"*0054*R0009*098", :bad_command},
        {"*0054*R0009X**228", :bad_command},
        {"*0054*R0009\tX*195", :bad_command}
      ]

      for {line, reason} <- cases do
        assert {:error, %Error{reason: ^reason}} = CommandString.decode(line), inspect(line)
      end
    end

    test "the reason's data points at the culprit" do
      assert {:error, %Error{data: "054"}} = CommandString.decode("*054*R0009X*138")
      assert {:error, %Error{data: "r0009X"}} = CommandString.decode("*0054*r0009X*218")
    end

    test "an A command may be empty, an unknown letter is decoded" do
      assert {:ok, %CommandString{commands: [%Command{set: :ack, number: 9, text: ""}]}} =
               CommandString.decode("*0054*A0009*081")

      assert {:ok, %CommandString{commands: [%Command{set: {:unknown, "Q"}, text: "HELLO"}]}} =
               CommandString.decode("*0054*Q0001HELLO*205")
    end

    test "set rules are SUN_COMM's, not the codec's" do
      # Two R commands break rule 1 of PROTOCOLS.md §1; syntactically the string is fine.
      line = "*0001*R0001WHERE*R0002WHERE*"
      assert {:ok, %CommandString{commands: [_, _]}} = CommandString.decode(line <> "134")
    end
  end

  test "encode refuses strings that could not be sent" do
    ok = Command.new(:robot, 1, "WHERE")

    for bad <- [
          %CommandString{sequence: 10_000, commands: [ok]},
          %CommandString{sequence: 1, commands: []},
          %CommandString{sequence: 1, commands: [%{ok | text: "A*B"}]},
          %CommandString{sequence: 1, commands: [%{ok | set: :gripper}]},
          %CommandString{sequence: 1, commands: [:robot]}
        ] do
      assert_raise ArgumentError, fn -> CommandString.encode(bad) end
    end

    assert_raise ArgumentError, fn ->
      CommandString.encode(%CommandString{sequence: 1, commands: [ok]}, bcc: :crc)
    end
  end

  describe "properties" do
    test "round trip" do
      property =
        :proper.forall(
          :proper_types.tuple([Generators.command_string(), Generators.mode()]),
          fn {string, mode} ->
            line = wire(string, bcc: mode)
            body = binary_part(line, 0, byte_size(line) - 2)

            String.ends_with?(line, "\r\n") and
              CommandString.decode(body, bcc: mode) == {:ok, string}
          end
        )

      assert_property(property, 150)
    end

    test "split anywhere through LineDecoder gives the same strings and an empty buffer" do
      property =
        :proper.forall(
          :proper_types.tuple([
            :proper_types.list(Generators.command_string()),
            Generators.mode(),
            Generators.cuts()
          ]),
          fn {strings, mode, cuts} ->
            bytes = IO.iodata_to_binary(Enum.map(strings, &CommandString.encode(&1, bcc: mode)))
            {lines, dec} = Generators.feed_all(LineDecoder.new(), Generators.chunks(bytes, cuts))

            Enum.map(lines, &CommandString.decode(&1, bcc: mode)) == Enum.map(strings, &{:ok, &1}) and
              LineDecoder.buffered(dec) == 0
          end
        )

      assert_property(property, 60)
    end

    test "random bytes never crash the decoders and never yield a command" do
      noise =
        :proper_types.list(
          :proper_types.union([
            :proper_types.binary(),
            :proper_types.exactly("*"),
            :proper_types.exactly("\r\n"),
            :proper_types.exactly("\n")
          ])
        )

      property =
        :proper.forall(
          :proper_types.tuple([noise, Generators.cuts(), Generators.mode()]),
          fn {parts, cuts, mode} ->
            bytes = IO.iodata_to_binary(parts)
            dec = LineDecoder.new(max_line: 64)
            {items, _dec} = Generators.feed_all(dec, Generators.chunks(bytes, cuts))

            Enum.all?(items, fn
              {:error, %Error{reason: :line_too_long}} -> true
              line -> match?({:error, %Error{}}, CommandString.decode(line, bcc: mode))
            end)
          end
        )

      assert_property(property, 200)
    end

    test "any single corrupted byte is rejected" do
      corruption =
        :proper_types.bind(
          :proper_types.tuple([Generators.command_string(), Generators.mode()]),
          fn {string, mode} ->
            line = wire(string, bcc: mode)

            :proper_types.tuple([
              :proper_types.exactly(mode),
              Generators.corruption(binary_part(line, 0, byte_size(line) - 2))
            ])
          end,
          false
        )

      property =
        :proper.forall(corruption, fn {mode, {line, pos, index}} ->
          match?(
            {:error, %Error{}},
            CommandString.decode(Generators.corrupt(line, pos, index), bcc: mode)
          )
        end)

      assert_property(property, 300)
    end
  end
end
