defmodule Vws.Codecs.WC.CommandString do
  @moduledoc """
  A command string from the workstation controller to SUN_COMM (PROTOCOLS.md §1, seed §2.3.2):

      *SSSS*M1*M2*…*Mn*BBB CR LF

  `SSSS` is the four-digit sequence number, each `Mi` a `Vws.Codecs.WC.Command`, and `BBB` the BCC of
  everything from the first `*` through the last `*`. `decode/2` takes the line without its
  terminator (as `Vws.Codecs.WC.LineDecoder` yields it) and accepts nothing but this exact form: a
  string needs at least one command, the sequence and command numbers exactly four digits, the
  BCC exactly three digits `000`–`255`.

  Step 1 of seed Table 1:

      iex> line = "*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*241"
      iex> {:ok, string} = Vws.Codecs.WC.CommandString.decode(line)
      iex> string.sequence
      54
      iex> Enum.map(string.commands, &{&1.set, &1.number, &1.text})
      [{:robot, 9, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"}, {:gripper, 4, "OPEN"}]
      iex> IO.iodata_to_binary(Vws.Codecs.WC.CommandString.encode(string))
      "*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*241\\r\\n"

  The checks run in this order, so the first failure names the reason: framing (`:malformed`),
  the BCC (`:bad_bcc`), at least one command (`:malformed`), the sequence (`:bad_sequence`), each
  command in turn (`:bad_command`). A string that breaks no syntax rule but repeats a set letter
  or mixes S with other commands is still decoded: those rules belong to SUN_COMM.
  """

  alias Vws.Codecs.WC.{BCC, Command, Error}

  @enforce_keys [:sequence, :commands]
  defstruct [:sequence, :commands]

  @type t :: %__MODULE__{sequence: 0..9999, commands: [Command.t(), ...]}

  @separator "*"
  @terminator "\r\n"
  @bcc_digits 3

  @doc """
  The bytes of `string` on the wire, CR LF included. Option `bcc: :sum | :xor` (default
  `:sum`). Raises `ArgumentError` for a string that could not be sent (no command, a number out
  of range, text with `*` or control characters).
  """
  @spec encode(t, keyword) :: iodata
  def encode(%__MODULE__{sequence: sequence, commands: commands} = string, opts \\ []) do
    mode = BCC.mode(opts)
    check!(string)

    covered = [
      @separator,
      Command.pad4(sequence),
      @separator
      | Enum.map(commands, fn %Command{letter: letter, number: number, text: text} ->
          [letter, Command.pad4(number), text, @separator]
        end)
    ]

    [covered, BCC.encode(BCC.compute(covered, mode)), @terminator]
  end

  defp check!(%__MODULE__{sequence: sequence, commands: commands}) do
    unless is_integer(sequence) and sequence in 0..9999,
      do: raise(ArgumentError, "sequence must be 0..9999, got #{inspect(sequence)}")

    unless is_list(commands) and commands != [],
      do: raise(ArgumentError, "a command string needs at least one command")

    Enum.each(commands, fn
      %Command{} = command ->
        with {:error, why} <- Command.check(command), do: raise(ArgumentError, why)

      other ->
        raise ArgumentError, "not a Vws.Codecs.WC.Command: #{inspect(other)}"
    end)
  end

  @doc """
  Decodes one line (no CR LF). Option `bcc: :sum | :xor` (default `:sum`).
  """
  @spec decode(binary, keyword) :: {:ok, t} | {:error, Error.t()}
  def decode(line, opts \\ []) when is_binary(line) do
    mode = BCC.mode(opts)

    with {:ok, covered, received} <- frame(line),
         :ok <- check_bcc(covered, received, mode),
         {:ok, sequence_field, command_fields} <- fields(line, covered),
         {:ok, sequence} <- sequence(sequence_field),
         {:ok, commands} <- commands(command_fields, []) do
      {:ok, %__MODULE__{sequence: sequence, commands: commands}}
    end
  end

  # `*` … `*` followed by exactly three BCC digits.
  defp frame(line) when byte_size(line) >= 2 + @bcc_digits do
    covered_size = byte_size(line) - @bcc_digits
    <<covered::binary-size(covered_size), field::binary>> = line

    with <<@separator, _::binary>> <- covered,
         @separator <- binary_part(covered, covered_size - 1, 1),
         {:ok, received} <- BCC.decode(field) do
      {:ok, covered, received}
    else
      _ -> malformed(line)
    end
  end

  defp frame(line), do: malformed(line)

  defp check_bcc(covered, received, mode) do
    case BCC.compute(covered, mode) do
      ^received ->
        :ok

      computed ->
        {:error, %Error{reason: :bad_bcc, data: %{computed: computed, received: received}}}
    end
  end

  defp fields(line, covered) do
    inner = binary_part(covered, 1, byte_size(covered) - 2)

    case :binary.split(inner, @separator, [:global]) do
      [sequence_field | [_ | _] = command_fields] -> {:ok, sequence_field, command_fields}
      [_no_commands] -> malformed(line)
    end
  end

  defp sequence(field) do
    case Command.digits(field) do
      {:ok, sequence} -> {:ok, sequence}
      :error -> {:error, %Error{reason: :bad_sequence, data: field}}
    end
  end

  defp commands([field | rest], acc) do
    case Command.parse(field) do
      {:ok, command} -> commands(rest, [command | acc])
      :error -> {:error, %Error{reason: :bad_command, data: field}}
    end
  end

  defp commands([], acc), do: {:ok, Enum.reverse(acc)}

  defp malformed(line), do: {:error, %Error{reason: :malformed, data: line}}
end
