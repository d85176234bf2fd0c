defmodule Vws.Codecs.WC.LineDecoder do
  @moduledoc """
  Splits the WC link's byte stream into lines (PROTOCOLS.md §1): each line ends at LF, and one CR
  before the LF is stripped. Lines are returned without their terminator, an empty line as `""`.

  A line longer than `max_line` bytes (default 1024, counted without its CR LF) is reported as
  exactly one `%Vws.Codecs.WC.Error{reason: :line_too_long}`, in its place among the lines, as soon as
  it is known to be too long (its first byte past `max_line` that is not its CR), and the rest
  of it is discarded up to its LF (decision, issue 15: the reply `E` comes at once; a sender that
  never ends the line gets its answer all the same). The decoder holds at most `max_line + 1`
  bytes (a full-length line and the CR that may end it); while discarding it holds none.

  Lines and the unfinished tail are copied out of the bytes fed, so neither pins a large received
  chunk: a peer sending megabytes with a short line at the end cannot make whoever keeps the
  line (a dialogue log, say) keep the megabytes too.

      iex> dec = Vws.Codecs.WC.LineDecoder.new()
      iex> {[], dec} = Vws.Codecs.WC.LineDecoder.feed(dec, "*0055*S0039ROB")
      iex> {lines, dec} = Vws.Codecs.WC.LineDecoder.feed(dec, "OT_CMD*032\\r\\nE\\r\\n")
      iex> lines
      ["*0055*S0039ROBOT_CMD*032", "E"]
      iex> Vws.Codecs.WC.LineDecoder.buffered(dec)
      0
  """

  alias Vws.Codecs.WC.Error

  @default_max_line 1024

  @enforce_keys [:max_line]
  defstruct buffer: "", max_line: @default_max_line, discarding: nil

  # `discarding` is nil, or {bytes_discarded_so_far, last_byte_was_cr?} while an overlong line runs
  # to its LF.
  @opaque t :: %__MODULE__{
            buffer: binary,
            max_line: pos_integer,
            discarding: nil | {non_neg_integer, boolean}
          }

  @doc "A decoder. Option `max_line:` the longest line accepted, in bytes (default 1024)."
  @spec new(keyword) :: t
  def new(opts \\ []) do
    case Keyword.get(opts, :max_line, @default_max_line) do
      max when is_integer(max) and max > 0 -> %__MODULE__{max_line: max}
      other -> raise ArgumentError, "max_line: must be a positive integer, got #{inspect(other)}"
    end
  end

  @doc "Feeds `bytes`; returns the lines completed by them (and errors, in order) and the decoder."
  @spec feed(t, binary) :: {[binary | {:error, Error.t()}], t}
  def feed(%__MODULE__{discarding: nil, buffer: buffer} = dec, bytes) when is_binary(bytes) do
    lines(dec, buffer <> bytes, [])
  end

  def feed(%__MODULE__{discarding: {count, _cr?}} = dec, bytes) when is_binary(bytes) do
    case :binary.match(bytes, "\n") do
      :nomatch when bytes == "" ->
        {[], dec}

      :nomatch ->
        {[], %{dec | discarding: {count + byte_size(bytes), :binary.last(bytes) == ?\r}}}

      {pos, 1} ->
        # the line was reported when it grew too long: its end says nothing more
        rest = binary_part(bytes, pos + 1, byte_size(bytes) - pos - 1)
        lines(%{dec | discarding: nil}, rest, [])
    end
  end

  @doc "How many bytes of an unfinished line the decoder holds."
  @spec buffered(t) :: non_neg_integer
  def buffered(%__MODULE__{buffer: buffer}), do: byte_size(buffer)

  defp lines(dec, data, acc) do
    case :binary.split(data, "\n") do
      [line, rest] ->
        line = strip_cr(line)

        item =
          if byte_size(line) > dec.max_line,
            do: too_long(byte_size(line), dec.max_line),
            else: :binary.copy(line)

        lines(dec, rest, [item | acc])

      [partial] ->
        if byte_size(strip_cr(partial)) > dec.max_line do
          cr? = :binary.last(partial) == ?\r
          acc = [too_long(byte_size(partial), dec.max_line) | acc]
          {Enum.reverse(acc), %{dec | buffer: "", discarding: {byte_size(partial), cr?}}}
        else
          {Enum.reverse(acc), %{dec | buffer: :binary.copy(partial)}}
        end
    end
  end

  defp strip_cr(line) do
    size = byte_size(line) - 1

    case line do
      <<content::binary-size(size), ?\r>> -> content
      _ -> line
    end
  end

  defp too_long(length, max_line),
    do: {:error, %Error{reason: :line_too_long, data: %{length: length, max_line: max_line}}}
end
