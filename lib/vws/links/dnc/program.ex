defmodule Vws.Links.DNC.Program do
  @moduledoc """
  NC part programs as they travel between the WC, the CEC's NC file and the GE-2000 (PROTOCOLS.md
  §1 "NC download", §2): pure functions, no processes.

  The CEC keeps a program as a list of lines (the lines the WC sent, without CR LF). On the DNC
  link the same program is ASCII text with LF ending every line (decision), cut into text blocks
  by `Vws.Links.DNC.Frame.split_text/2`. `to_text/1` and `from_text/1` convert between the two without
  losing a byte, so a program comes back from the GE-2000 exactly as it went.

  The program number is the first `O` word (ISO) or `:` word (EIA), as six digits with leading
  zeroes; it names the file `nnnnnn.PRO` on the GE-2000. Comments in parentheses are skipped.

      iex> lines = ["%", "O1234 (BRACKET)", "N10 G90 G00 X0 Y0", "N20 M30", "%"]
      iex> Vws.Links.DNC.Program.file_name(lines)
      {:ok, "001234.PRO"}
      iex> text = Vws.Links.DNC.Program.to_text(lines)
      "%\\nO1234 (BRACKET)\\nN10 G90 G00 X0 Y0\\nN20 M30\\n%\\n"
      iex> Vws.Links.DNC.Program.from_text(text) == lines
      true
  """

  # the largest size the GE-2000's directory can say (six digits): PROTOCOLS.md §2
  @max_stored_bytes 999_999

  @doc """
  The largest program the GE-2000 can store and its directory describe: 999,999 bytes, the
  six-digit size field (PROTOCOLS.md §2 "Program size limit"). The one home of that limit.
  """
  @spec max_stored_bytes() :: pos_integer
  def max_stored_bytes, do: @max_stored_bytes

  @doc """
  Whether a program (its text, or its size in bytes) may be stored — at the end of DOWNLOAD_HP,
  in the program library, by DOWNLOAD_GE, as a program the GE-2000 sends — with the error every
  door answers. A drip feed stores nothing and is not limited.

      iex> Vws.Links.DNC.Program.check_size("%\\nO1\\n%\\n")
      :ok
      iex> Vws.Links.DNC.Program.check_size(1_330_000)
      {:error, "PROGRAM TOO LARGE 1330000 BYTES (LIMIT 999999)"}
  """
  @spec check_size(binary | non_neg_integer) :: :ok | {:error, String.t()}
  def check_size(text) when is_binary(text), do: check_size(byte_size(text))
  def check_size(bytes) when is_integer(bytes) and bytes <= @max_stored_bytes, do: :ok

  def check_size(bytes) when is_integer(bytes),
    do: {:error, "PROGRAM TOO LARGE #{bytes} BYTES (LIMIT #{@max_stored_bytes})"}

  # X3.28 transmission controls: never in the non-transparent text of the DNC link (see
  # Vws.Links.DNC.Frame's moduledoc), plus CR and LF, which cannot be inside one of the CEC's lines.
  @not_in_text [0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x10, 0x15, 0x16, 0x17]
  @not_in_line [?\r, ?\n | @not_in_text]

  @doc """
  The program number of a program (lines or text): `{:ok, "nnnnnn"}`, `{:error, :no_program_number}`
  when it has no `O`/`:` word, `{:error, :bad_program_number}` when that word has more than six
  digits.

      iex> Vws.Links.DNC.Program.number([":77", "N10 G00"])
      {:ok, "000077"}
      iex> Vws.Links.DNC.Program.number(["N10 G00 (NO O WORD HERE)"])
      {:error, :no_program_number}
  """
  @spec number([binary] | binary) ::
          {:ok, binary} | {:error, :no_program_number | :bad_program_number}
  def number(text) when is_binary(text), do: number(String.split(text, "\n"))

  def number(lines) when is_list(lines) do
    Enum.find_value(lines, {:error, :no_program_number}, fn line ->
      line = line |> String.upcase() |> String.replace(~r/\([^)]*\)?/, "")

      case Regex.run(~r/(?<![A-Z])[O:]\s*(\d+)/, line, capture: :all_but_first) do
        [digits] when byte_size(digits) <= 6 -> {:ok, String.pad_leading(digits, 6, "0")}
        [_digits] -> {:error, :bad_program_number}
        nil -> nil
      end
    end)
  end

  @doc "The GE-2000 file name of a program, `nnnnnn.PRO`; errors as `number/1`."
  @spec file_name([binary] | binary) ::
          {:ok, binary} | {:error, :no_program_number | :bad_program_number}
  def file_name(program) do
    with {:ok, n} <- number(program), do: {:ok, n <> ".PRO"}
  end

  @doc """
  Whether DNC text is a whole program (PROTOCOLS.md §2 "A program is whole or it is nothing"): its
  last line is `%` (blanks around it allowed) and ends with LF. A transmission cut short — an ENQ
  damaged into EOT looks like a normal end — is not.

      iex> Vws.Links.DNC.Program.complete?("%\\nO1\\nM30\\n%\\n")
      true
      iex> Vws.Links.DNC.Program.complete?("%\\nO1\\nM30\\n")
      false
  """
  @spec complete?(binary) :: boolean
  def complete?(text) when is_binary(text) do
    if String.ends_with?(text, "\n") do
      case from_text(text) do
        [_ | _] = lines -> String.trim(List.last(lines)) == "%"
        [] -> false
      end
    else
      false
    end
  end

  @doc "The program as DNC text: every line followed by LF."
  @spec to_text([binary]) :: binary
  def to_text(lines), do: IO.iodata_to_binary(Enum.map(lines, &[&1, ?\n]))

  @doc """
  The lines of DNC text: split at LF; the LF ending the last line does not make an empty line.
  A CR before an LF is kept as part of the line (the WC link cannot carry it, so it is reported
  by `check_lines/1`, not silently dropped).
  """
  @spec from_text(binary) :: [binary]
  def from_text(""), do: []

  def from_text(text) do
    lines = String.split(text, "\n")
    if List.last(lines) == "", do: Enum.drop(lines, -1), else: lines
  end

  @doc """
  Checks that every line can travel on both links: `:ok`, or `{:error, line_number}` (1-based) for
  the first line holding a transmission control character, CR or LF.

      iex> Vws.Links.DNC.Program.check_lines(["N10 G00", <<"N20 ", 2, "X">>])
      {:error, 2}
  """
  @spec check_lines([binary]) :: :ok | {:error, pos_integer}
  def check_lines(lines) do
    lines
    |> Enum.with_index(1)
    |> Enum.find_value(:ok, fn {line, i} ->
      if :binary.match(line, Enum.map(@not_in_line, &<<&1>>)) != :nomatch, do: {:error, i}
    end)
  end

  @doc "True when `text` may be sent in DNC text blocks (no transmission control characters)."
  @spec sendable?(binary) :: boolean
  def sendable?(text), do: :binary.match(text, Enum.map(@not_in_text, &<<&1>>)) == :nomatch
end
