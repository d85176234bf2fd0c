defmodule Vws.Codecs.WC.ProgramCRC do
  @moduledoc """
  The whole-program check of the WC link (PROTOCOLS.md §1 "Whole-program check"): the
  CRC-16/ARC (`Vws.Codecs.CRC16`) of an NC program's text as stored — all its lines from the
  first to the closing `%`, each ending LF — written as four upper-case hex digits.

  Why: every program line carries only the link's 8-bit-sum BCC, which two flipped bits in one
  line pass about once in 27. The WC names the CRC in `M nnnn DOWNLOAD_HP(cccc)`; SUN_COMM
  answers the closing `%` with `A` + count + `/` + the CRC of what it stored, and sends it at the
  end of an UPLOAD_SUN as the closing line's text `%/cccc`.

      iex> Vws.Codecs.WC.ProgramCRC.compute(["%", "O1", "M30", "%"])
      0x8B3C
      iex> Vws.Codecs.WC.ProgramCRC.format(0x8B3C)
      "8B3C"
      iex> Vws.Codecs.WC.ProgramCRC.parse("8B3C")
      {:ok, 0x8B3C}
      iex> Vws.Codecs.WC.ProgramCRC.closing_line("%", 0x8B3C)
      "%/8B3C"
      iex> Vws.Codecs.WC.ProgramCRC.split_closing("%/8B3C")
      {:ok, "%", 0x8B3C}
  """

  alias Vws.Codecs.CRC16

  @type crc :: 0..0xFFFF

  @doc "The CRC-16/ARC of a program given as its lines (without line ends)."
  @spec compute([binary]) :: crc
  def compute(lines) when is_list(lines),
    do: Enum.reduce(lines, 0, fn line, crc -> CRC16.compute([line, ?\n], crc) end)

  @doc """
  The CRC of the program so far (`crc`) continued with one more line: what a receiver keeps
  while the lines come, `compute(lines) == Enum.reduce(lines, 0, &add_line(&2, &1))`.
  """
  @spec add_line(crc, binary) :: crc
  def add_line(crc, line) when is_binary(line), do: CRC16.compute([line, ?\n], crc)

  @doc "Four upper-case hex digits."
  @spec format(crc) :: <<_::32>>
  def format(crc) when is_integer(crc) and crc in 0..0xFFFF,
    do: crc |> Integer.to_string(16) |> String.pad_leading(4, "0")

  @doc """
  Reads four hex digits (the WC writes upper case; lower case is taken as well, as every
  command's text is). Anything else is `:error`.

      iex> Vws.Codecs.WC.ProgramCRC.parse("12G4")
      :error
  """
  @spec parse(binary) :: {:ok, crc} | :error
  def parse(<<_::binary-size(4)>> = hex) do
    if hex =~ ~r/^[0-9A-Fa-f]{4}$/, do: {:ok, String.to_integer(hex, 16)}, else: :error
  end

  def parse(_), do: :error

  @doc "The text of UPLOAD_SUN's closing line: the program's last line, `/`, the CRC."
  @spec closing_line(binary, crc) :: binary
  def closing_line(last, crc), do: last <> "/" <> format(crc)

  @doc """
  Splits the text of a closing line sent with the CRC (`%/cccc`) into the line as stored and
  the CRC; `:error` when the text does not end in `/` + four hex digits.

      iex> Vws.Codecs.WC.ProgramCRC.split_closing("%")
      :error
  """
  @spec split_closing(binary) :: {:ok, binary, crc} | :error
  def split_closing(text) when byte_size(text) >= 5 do
    size = byte_size(text) - 5

    with <<last::binary-size(size), ?/, hex::binary-size(4)>> <- text,
         {:ok, crc} <- parse(hex) do
      {:ok, last, crc}
    else
      _ -> :error
    end
  end

  def split_closing(_text), do: :error
end
