defmodule Vws.Codecs.WC.Reply do
  @moduledoc """
  The short lines of the WC link other than command strings (PROTOCOLS.md §1, seed §2.3.2):
  SUN_COMM's replies and the lines of an NC program transfer. Each is one line ending in CR LF
  and, except `E` and `A`, ends in the BCC of the bytes before it.

  | term                    | on the wire                          | sent by                      |
  |-------------------------|--------------------------------------|------------------------------|
  | `:nak`                  | `E`                                  | the receiver of a bad line   |
  | `{:line_ack, n}`        | `A` `nnnn` BBB                       | the receiver of NC line `n`, stored |
  | `{:line_ack, n, crc}`   | `A` `nnnn` `/` `cccc` BBB            | CEC, the closing `%` of a download: `n` lines stored, `cccc` their CRC |
  | `{:ack, seq}`           | `05A` `SSSS` BBB                     | CEC, string received intact  |
  | `{:status, n, text}`    | `NN` `S` `nnnn` text BBB             | CEC, answer to status command `n` |
  | `{:line, n, text}`      | `nnnn` text BBB                      | NC download/upload, either way |

  NC program lines are numbered (0001, 0002, …, after 9999 comes 0000) and their answers name the
  line stored, with a BCC, so a damaged answer is seen as damaged and a resent line is recognised
  by its number (PROTOCOLS.md §1 "NC download"): one bit turns `A` into `E` (0x41/0x45), so an
  unchecked one-letter answer could make a line be stored twice or skipped.

  The answer to a download's closing `%` also names the CRC-16/ARC of the program stored
  (`Vws.Codecs.WC.ProgramCRC`, PROTOCOLS.md §1 "Whole-program check"), so the two ends agree on
  the whole program, not only on each line.

  `NN` is the two-digit length of `S` + `nnnn` + text, so a status text has at most
  94 characters (`truncate_status_text/1`). Texts are printable ASCII (0x20–0x7E).

  `decode/2` reads what the WC receives after a command string (`:nak`, `:line_ack`, `{:ack, _}`,
  `{:status, _, _}`); `decode_line/2` reads an NC program line. A program line can look like a
  reply, so the caller, knowing whether a transfer is under way, picks the decoder.

      iex> IO.iodata_to_binary(Vws.Codecs.WC.Reply.encode({:status, 39, "0009DONE"}))
      "13S00390009DONE114\\r\\n"
      iex> Vws.Codecs.WC.Reply.decode("05A0054111")
      {:ok, {:ack, 54}}
  """

  alias Vws.Codecs.WC.{BCC, Command, Error, ProgramCRC}

  @type t ::
          :nak
          | {:line_ack, 0..9999}
          | {:line_ack, 0..9999, ProgramCRC.crc()}
          | {:ack, 0..9999}
          | {:status, 0..9999, String.t()}
          | {:line, 0..9999, String.t()}

  @nak "E"
  @line_ack "A"
  @line_ack_length 8
  @closing_ack_length 13
  @ack_length "05"
  @ack "A"
  @status "S"
  @max_status_text 94
  @bcc_digits 3
  @terminator "\r\n"

  @doc """
  The bytes of `reply` on the wire, CR LF included. Option `bcc: :sum | :xor` (default `:sum`).
  Raises `ArgumentError` for a reply `validate/1` rejects (a programmer error: use
  `truncate_status_text/1` on a status text of unknown length).
  """
  @spec encode(t, keyword) :: iodata
  def encode(reply, opts \\ []) do
    mode = BCC.mode(opts)

    case validate(reply) do
      :ok ->
        [body(reply, mode), @terminator]

      {:error, error} ->
        raise ArgumentError, "cannot encode #{inspect(reply)}: #{Exception.message(error)}"
    end
  end

  defp body(:nak, _mode), do: @nak
  defp body({:line_ack, n}, mode), do: with_bcc([@line_ack, Command.pad4(n)], mode)

  defp body({:line_ack, n, crc}, mode),
    do: with_bcc([@line_ack, Command.pad4(n), "/", ProgramCRC.format(crc)], mode)

  defp body({:ack, seq}, mode), do: with_bcc([@ack_length, @ack, Command.pad4(seq)], mode)

  defp body({:status, number, text}, mode) do
    length = byte_size(@status) + 4 + byte_size(text)
    with_bcc([pad2(length), @status, Command.pad4(number), text], mode)
  end

  defp body({:line, n, text}, mode), do: with_bcc([Command.pad4(n), text], mode)

  defp with_bcc(data, mode), do: [data, BCC.encode(BCC.compute(data, mode))]

  defp pad2(n) when n < 10, do: ["0", Integer.to_string(n)]
  defp pad2(n), do: Integer.to_string(n)

  @doc """
  Whether `reply` can be encoded: `:ok`, or the `Vws.Codecs.WC.Error` saying why not
  (`:text_too_long` for a status text over 94 characters).
  """
  @spec validate(term) :: :ok | {:error, Error.t()}
  def validate(reply)
  def validate(:nak), do: :ok
  def validate({:line_ack, n}) when is_integer(n) and n in 0..9999, do: :ok

  def validate({:line_ack, n, crc})
      when is_integer(n) and n in 0..9999 and is_integer(crc) and crc in 0..0xFFFF,
      do: :ok

  def validate({:ack, seq}) when is_integer(seq) and seq in 0..9999, do: :ok
  def validate({:ack, seq}), do: {:error, %Error{reason: :bad_sequence, data: seq}}

  def validate({:status, number, text} = reply) when is_integer(number) and number in 0..9999 do
    cond do
      not (is_binary(text) and printable?(text)) ->
        {:error, %Error{reason: :malformed, data: reply}}

      byte_size(text) > @max_status_text ->
        {:error,
         %Error{reason: :text_too_long, data: %{length: byte_size(text), max: @max_status_text}}}

      true ->
        :ok
    end
  end

  def validate({:line, n, text} = reply) when is_integer(n) and n in 0..9999 do
    if is_binary(text) and printable?(text),
      do: :ok,
      else: {:error, %Error{reason: :malformed, data: reply}}
  end

  def validate(reply), do: {:error, %Error{reason: :malformed, data: reply}}

  @doc """
  `text` cut to the 94 characters a status reply can carry.

      iex> byte_size(Vws.Codecs.WC.Reply.truncate_status_text(String.duplicate("X", 120)))
      94
  """
  @spec truncate_status_text(String.t()) :: String.t()
  def truncate_status_text(text) when byte_size(text) > @max_status_text,
    do: binary_part(text, 0, @max_status_text)

  def truncate_status_text(text) when is_binary(text), do: text

  @doc """
  Decodes a reply the WC receives after sending a command string (one line, no CR LF):
  `:nak`, `{:line_ack, n}`, `{:line_ack, n, crc}`, `{:ack, seq}` or `{:status, number, text}`.
  Option `bcc:`.

      iex> Vws.Codecs.WC.Reply.decode("A0007008")
      {:ok, {:line_ack, 7}}
      iex> Vws.Codecs.WC.Reply.decode("A0005/52D5021")
      {:ok, {:line_ack, 5, 0x52D5}}
  """
  @spec decode(binary, keyword) ::
          {:ok,
           :nak
           | {:line_ack, 0..9999}
           | {:line_ack, 0..9999, ProgramCRC.crc()}
           | {:ack, 0..9999}
           | {:status, 0..9999, String.t()}}
          | {:error, Error.t()}
  def decode(line, opts \\ [])
  def decode(@nak, _opts), do: {:ok, :nak}

  def decode(<<@line_ack, _::binary>> = line, opts) when byte_size(line) == @line_ack_length do
    with {:ok, <<@line_ack, field::binary-size(4)>>} <- checked(line, BCC.mode(opts)),
         {:ok, n} <- Command.digits(field) do
      {:ok, {:line_ack, n}}
    else
      {:error, %Error{}} = error -> error
      _ -> malformed(line)
    end
  end

  def decode(<<@line_ack, _::binary>> = line, opts) when byte_size(line) == @closing_ack_length do
    with {:ok, <<@line_ack, field::binary-size(4), ?/, hex::binary-size(4)>>} <-
           checked(line, BCC.mode(opts)),
         {:ok, n} <- Command.digits(field),
         true <- hex == String.upcase(hex),
         {:ok, crc} <- ProgramCRC.parse(hex) do
      {:ok, {:line_ack, n, crc}}
    else
      {:error, %Error{}} = error -> error
      _ -> malformed(line)
    end
  end

  def decode(line, opts) when is_binary(line) do
    mode = BCC.mode(opts)

    with {:ok, body} <- checked(line, mode),
         <<nn::binary-size(2), rest::binary>> <- body,
         {:ok, length} when length == byte_size(rest) <- nn_length(nn) do
      reply(rest, line)
    else
      {:error, %Error{}} = error -> error
      _ -> malformed(line)
    end
  end

  defp nn_length(<<a, b>>) when a in ?0..?9 and b in ?0..?9, do: {:ok, (a - ?0) * 10 + (b - ?0)}
  defp nn_length(_), do: :error

  defp reply(<<@ack, field::binary>>, _line) when byte_size(field) == 4 do
    case Command.digits(field) do
      {:ok, seq} -> {:ok, {:ack, seq}}
      :error -> {:error, %Error{reason: :bad_sequence, data: field}}
    end
  end

  defp reply(<<@status, field::binary-size(4), text::binary>>, line) do
    with {:ok, number} <- Command.digits(field),
         true <- printable?(text) do
      {:ok, {:status, number, text}}
    else
      _ -> malformed(line)
    end
  end

  defp reply(_rest, line), do: malformed(line)

  @doc """
  Decodes an NC program line, number + text + BCC (one line, no CR LF). Option `bcc:`.

      iex> Vws.Codecs.WC.Reply.decode_line("0012%232")
      {:ok, {:line, 12, "%"}}
  """
  @spec decode_line(binary, keyword) :: {:ok, {:line, 0..9999, String.t()}} | {:error, Error.t()}
  def decode_line(line, opts \\ []) when is_binary(line) do
    mode = BCC.mode(opts)

    with {:ok, body} <- checked(line, mode),
         <<field::binary-size(4), text::binary>> <- body,
         {:ok, n} <- Command.digits(field),
         true <- printable?(text) do
      {:ok, {:line, n, text}}
    else
      {:error, %Error{}} = error -> error
      _ -> malformed(line)
    end
  end

  # The bytes before a valid BCC field, or why there are none.
  defp checked(line, mode) when byte_size(line) >= @bcc_digits do
    size = byte_size(line) - @bcc_digits
    <<body::binary-size(size), field::binary>> = line

    case BCC.decode(field) do
      {:ok, received} ->
        case BCC.compute(body, mode) do
          ^received ->
            {:ok, body}

          computed ->
            {:error, %Error{reason: :bad_bcc, data: %{computed: computed, received: received}}}
        end

      :error ->
        malformed(line)
    end
  end

  defp checked(line, _mode), do: malformed(line)

  defguardp printable_byte(byte) when byte in 0x20..0x7E

  # eight bytes a step where it can (a step costs what a byte would)
  defp printable?(<<a, b, c, d, e, f, g, h, rest::binary>>)
       when printable_byte(a) and printable_byte(b) and printable_byte(c) and printable_byte(d) and
              printable_byte(e) and printable_byte(f) and printable_byte(g) and printable_byte(h),
       do: printable?(rest)

  defp printable?(<<byte, rest::binary>>) when printable_byte(byte), do: printable?(rest)
  defp printable?(<<>>), do: true
  defp printable?(_), do: false

  defp malformed(line), do: {:error, %Error{reason: :malformed, data: line}}
end
