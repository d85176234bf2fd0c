defmodule Vws.Links.DNC.Report do
  @moduledoc """
  The fixed formats the GE-2000 sends after an `R` command (PROTOCOLS.md §2, decisions): the
  status report answering `RNL` and the tool-offset table answering `RNO` `TOFFSET`. Pure
  functions shared by MONARCH (which reads them) and `Vws.Sim.GE2000` (which writes them).

    * Status report: `STATE=ACTIVE|IDLE;PROG=nnnnnn;ALARM=n` — the machine state, the selected
      program (`000000` when none) and the alarm number (`0` when none).
    * Tool-offset table: one line per offset, `nn ±ddd.dddd`, LF after each line; `nn` is the line
      number the WC names in `TABLE(L1/…/Ln)`.

      iex> Vws.Links.DNC.Report.status(%{state: :active, program: "001234", alarm: 0})
      "STATE=ACTIVE;PROG=001234;ALARM=0"
      iex> Vws.Links.DNC.Report.parse_status("STATE=IDLE;PROG=000000;ALARM=4\\n")
      {:ok, %{state: :idle, program: "000000", alarm: 4}}
      iex> Vws.Links.DNC.Report.offsets([{1, 12.5}, {2, -0.25}])
      "01 +012.5000\\n02 -000.2500\\n"
      iex> Vws.Links.DNC.Report.parse_offsets("01 +012.5000\\n02 -000.2500\\n")
      {:ok, %{1 => "+012.5000", 2 => "-000.2500"}}
  """

  @type status :: %{state: :active | :idle, program: binary, alarm: non_neg_integer}

  @doc "The status report text."
  @spec status(status) :: binary
  def status(%{state: state, program: program, alarm: alarm}) do
    "STATE=#{state |> to_string() |> String.upcase()};PROG=#{program};ALARM=#{alarm}"
  end

  @doc "Reads a status report; surrounding blanks and line ends are ignored."
  @spec parse_status(binary) :: {:ok, status} | {:error, :bad_status_report}
  def parse_status(text) do
    case Regex.run(~r/^STATE=(ACTIVE|IDLE);PROG=(\d{6});ALARM=(\d{1,3})$/, String.trim(text)) do
      [_, state, program, alarm] ->
        {:ok,
         %{
           state: if(state == "ACTIVE", do: :active, else: :idle),
           program: program,
           alarm: String.to_integer(alarm)
         }}

      nil ->
        {:error, :bad_status_report}
    end
  end

  @typedoc "A directory entry: file name, size in bytes, CRC-16/ARC of the file's bytes."
  @type entry :: %{name: binary, size: non_neg_integer, crc: 0..0xFFFF}

  @doc """
  The directory text answering `RNF` (PROTOCOLS.md §2 "Directory"): one line per file,
  `nnnnnn.PRO bbbbbb cccc` — name, size (six digits), CRC-16/ARC of the file's bytes (four upper
  case hex digits) — LF after each, in the order given.

      iex> Vws.Links.DNC.Report.directory([{"001234.PRO", "123456789"}])
      "001234.PRO 000009 BB3D\\n"
  """
  @spec directory([{binary, binary}]) :: binary
  def directory(files) do
    IO.iodata_to_binary(
      for {name, bytes} <- files do
        %{size: size, crc: crc} = entry(name, bytes)

        [
          name,
          ?\s,
          String.pad_leading(Integer.to_string(size), 6, "0"),
          ?\s,
          String.pad_leading(Integer.to_string(crc, 16), 4, "0"),
          ?\n
        ]
      end
    )
  end

  @doc "The directory entry of a file's bytes."
  @spec entry(binary, binary) :: entry
  def entry(name, bytes),
    do: %{name: name, size: byte_size(bytes), crc: Vws.Codecs.CRC16.compute(bytes)}

  @doc """
  Reads a directory into `%{name => entry}`; blank lines are skipped. A line that is not
  `nnnnnn.PRO|GSU bbbbbb cccc` but begins with a file name makes that one file `:unreadable`
  (a size over six digits, a damaged CRC): it never fails what is said of the others
  (PROTOCOLS.md §2 "Program size limit"). A line that names no file is passed over; a
  directory none of whose lines names a file is an error.

      iex> Vws.Links.DNC.Report.parse_directory("001234.PRO 000009 BB3D\\n")
      {:ok, %{"001234.PRO" => %{name: "001234.PRO", size: 9, crc: 0xBB3D}}}
      iex> Vws.Links.DNC.Report.parse_directory("001234.PRO 000009 BB3D\\n007777.PRO 1330000 0A1B\\n")
      {:ok, %{"001234.PRO" => %{name: "001234.PRO", size: 9, crc: 0xBB3D}, "007777.PRO" => :unreadable}}
  """
  @spec parse_directory(binary) ::
          {:ok, %{binary => entry | :unreadable}} | {:error, {:bad_line, binary}}
  def parse_directory(text) do
    lines = text |> String.split(["\r\n", "\n"]) |> Enum.reject(&(String.trim(&1) == ""))

    entries =
      Enum.reduce(lines, %{}, fn line, acc ->
        case directory_line(line) do
          {:ok, entry} ->
            Map.put(acc, entry.name, entry)

          :error ->
            case line_name(line) do
              {:ok, name} -> Map.put(acc, name, :unreadable)
              :error -> acc
            end
        end
      end)

    if entries == %{} and lines != [],
      do: {:error, {:bad_line, hd(lines)}},
      else: {:ok, entries}
  end

  defp line_name(<<number::binary-6, ".", ext::binary-3, rest::binary>>)
       when ext in ["PRO", "GSU"] do
    if all?(number, &(&1 in ?0..?9)) and (rest == "" or binary_part(rest, 0, 1) == " "),
      do: {:ok, number <> "." <> ext},
      else: :error
  end

  defp line_name(_line), do: :error

  # `nnnnnn.PRO|GSU bbbbbb cccc` by binary matching, not a regular expression: the program
  # library reads directories of 10,000 lines (bench/library.exs)
  defp directory_line(
         <<number::binary-6, ".", ext::binary-3, " ", size::binary-6, " ", crc::binary-4>>
       )
       when ext in ["PRO", "GSU"] do
    if all?(number, &(&1 in ?0..?9)) and all?(size, &(&1 in ?0..?9)) and
         all?(crc, &(&1 in ?0..?9 or &1 in ?A..?F)) do
      {:ok,
       %{
         name: number <> "." <> ext,
         size: String.to_integer(size),
         crc: String.to_integer(crc, 16)
       }}
    else
      :error
    end
  end

  defp directory_line(_line), do: :error

  defp all?(bytes, ok?), do: bytes |> :binary.bin_to_list() |> Enum.all?(ok?)

  @doc "The tool-offset table text for `[{line, value}]` (|value| < 1000)."
  @spec offsets([{0..99, number}]) :: binary
  def offsets(table) do
    IO.iodata_to_binary(
      for {n, value} <- table do
        [String.pad_leading(Integer.to_string(n), 2, "0"), ?\s, offset(value), ?\n]
      end
    )
  end

  @doc """
  One offset value as `±ddd.dddd`.

      iex> Vws.Links.DNC.Report.offset(-3.14159)
      "-003.1416"
  """
  @spec offset(number) :: binary
  def offset(value) do
    sign = if value < 0, do: "-", else: "+"
    digits = :erlang.float_to_binary(abs(value) * 1.0, decimals: 4)
    sign <> String.pad_leading(digits, 8, "0")
  end

  @doc """
  Reads a tool-offset table into `%{line => "±ddd.dddd"}` (the values kept as the GE-2000 wrote
  them); blank lines are skipped, any other line that is not `nn ±ddd.dddd` is an error.
  """
  @spec parse_offsets(binary) ::
          {:ok, %{non_neg_integer => binary}} | {:error, {:bad_line, binary}}
  def parse_offsets(text) do
    text
    |> String.split(["\r\n", "\n"])
    |> Enum.reject(&(String.trim(&1) == ""))
    |> Enum.reduce_while({:ok, %{}}, fn line, {:ok, acc} ->
      case Regex.run(~r/^\s*(\d{1,3})\s+([+-]\d{3}\.\d{4})\s*$/, line) do
        [_, n, value] -> {:cont, {:ok, Map.put(acc, String.to_integer(n), value)}}
        nil -> {:halt, {:error, {:bad_line, line}}}
      end
    end)
  end
end
