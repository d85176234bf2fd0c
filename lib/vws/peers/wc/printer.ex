defmodule Vws.Peers.WC.Printer do
  @moduledoc """
  The WC's dialogue printed as it happens, for `mix vws.wc --script` (`Vws.Peers.WC.CLI`) and
  `mix vws.demo` (`Vws.Ops.Demo`): one row per line on the link — the time since the WC
  connected, `→` for WC to CEC or `←` for CEC to WC, the line as on the wire, and its meaning;
  script steps on rows of their own (`──`). A status query answered exactly as the previous one
  is not printed again; a row `… asked N more times` says how often it was repeated.

  Wire text is bytes: `printable/1` and `readable/1` keep a damaged byte from reaching the
  terminal.
  """

  @typedoc "What the printer holds between events (a status query waiting for its answer, the repeats folded)."
  @type t :: %{
          held: map | nil,
          last: {String.t(), String.t()} | nil,
          repeats: non_neg_integer,
          since: integer | nil,
          until: integer | nil
        }

  @doc "A printer that has printed nothing yet."
  @spec new() :: t
  def new, do: %{held: nil, last: nil, repeats: 0, since: nil, until: nil}

  @doc """
  Prints one event of the client (`Vws.Peers.WC.Client.Event`), or holds a status query until its
  answer shows whether it repeats; returns the printer.
  """
  @spec print_event(map, t) :: t
  def print_event(%{kind: :status_query} = event, printer) do
    printer = release(printer)
    %{printer | held: event}
  end

  def print_event(%{kind: :status} = answer, %{held: query} = printer) when query != nil do
    pair = {query.meaning, answer.meaning}

    if pair == printer.last do
      %{
        printer
        | held: nil,
          repeats: printer.repeats + 1,
          since: printer.since || query.at,
          until: answer.at
      }
    else
      printer = flush(%{printer | held: nil})
      row(query)
      row(answer)
      %{printer | last: pair}
    end
  end

  def print_event(event, printer) do
    printer = flush(release(printer))
    row(event)
    %{printer | last: nil}
  end

  defp release(%{held: nil} = printer), do: printer

  defp release(%{held: query} = printer) do
    printer = flush(printer)
    row(query)
    %{printer | held: nil, last: nil}
  end

  @doc "Prints the row of the repeats folded so far (a script's end, or a line other than a status)."
  @spec flush(t) :: t
  def flush(%{repeats: 0} = printer), do: printer

  def flush(printer) do
    span = seconds(printer.until - printer.since)

    IO.puts(
      "          … asked #{printer.repeats} more #{plural(printer.repeats, "time")} over #{span}: same answer"
    )

    %{printer | repeats: 0, since: nil, until: nil}
  end

  defp row(%{direction: :note, meaning: meaning, at: at}),
    do: IO.puts("#{time(at)}  ── #{readable(meaning)}")

  defp row(%{direction: direction, line: line, meaning: meaning, at: at}) do
    arrow = if direction == :sent, do: "→", else: "←"

    IO.puts(
      "#{time(at)}  #{arrow} #{String.pad_trailing(printable(line || ""), 52)}  #{readable(meaning)}"
    )
  end

  @doc ~S"""
  A line as it was on the wire, readable on a terminal: printable ASCII as it is, every other
  byte (a bit flipped by a noisy line, a control character) as `\xNN`, and `\` itself as `\\`.
  Wire text is bytes, not UTF-8: a damaged byte must not reach the terminal, nor stop the
  printing (`IO.puts/1` raises on a binary that is not valid UTF-8).

      iex> Vws.Peers.WC.Printer.printable("11S0090ACTI" <> <<0xD6>> <> "E058")
      "11S0090ACTI\\xD6E058"
      iex> Vws.Peers.WC.Printer.printable("a\tb\\c")
      "a\\x09b\\\\c"
  """
  @spec printable(binary) :: String.t()
  def printable(bytes) when is_binary(bytes) do
    for <<byte <- bytes>>, into: "" do
      cond do
        byte == ?\\ -> "\\\\"
        byte in 0x20..0x7E -> <<byte>>
        true -> hex(byte)
      end
    end
  end

  @doc ~S"""
  Text for a person (a meaning, a script step, the summary's reason) made safe to print: valid
  UTF-8 that prints stays as it is; a byte that is not valid UTF-8 (a damaged byte quoted from
  the wire) or a control character becomes `\xNN`.

      iex> Vws.Peers.WC.Printer.readable("MONARCH: ACTI" <> <<0xD6>> <> "E — ×20")
      "MONARCH: ACTI\\xD6E — ×20"
  """
  @spec readable(binary) :: String.t()
  def readable(text) when is_binary(text), do: readable(text, "")

  defp readable(<<c::utf8, rest::binary>>, acc) when c >= 0x20 and c not in 0x7F..0x9F,
    do: readable(rest, <<acc::binary, c::utf8>>)

  defp readable(<<byte, rest::binary>>, acc), do: readable(rest, acc <> hex(byte))
  defp readable(<<>>, acc), do: acc

  defp hex(byte), do: "\\x" <> String.pad_leading(Integer.to_string(byte, 16), 2, "0")

  defp time(ms), do: String.pad_leading(seconds(ms), 8)
  defp seconds(ms), do: :erlang.float_to_binary(ms / 1000, decimals: 3) <> "s"
  defp plural(1, word), do: word
  defp plural(_, word), do: word <> "s"
end
