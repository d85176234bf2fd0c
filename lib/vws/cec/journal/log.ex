defmodule Vws.CEC.Journal.Log do
  @moduledoc """
  The journal's file format: framed records, each with its own checksums, and an end mark.

  A frame is

      "VJ" kind:8 length:32 header_crc:32  payload(length bytes)  payload_crc:32

  `header_crc` is the CRC-32 of the seven bytes before it, `payload_crc` the CRC-32 of the
  payload. Kind `1` is a record (its payload `:erlang.term_to_binary/1` of the record), kind
  `#{inspect(?E)}` (`E`) the end mark, with an empty payload. Every append writes the record and
  an end mark after it, and the next append writes over that end mark, so a journal that was
  written whole ends with exactly one end mark; one cut short — anywhere, even between two
  frames — does not.

  `parse/1` reads a log into items in file order:

    * `{:record, offset, payload}` — a frame whose checksums hold
    * `{:kind, offset, kind}` — a whole frame of a kind this version does not know (a newer one)
    * `{:damaged, offset, why}` — bytes from `offset` that are no frame: `why` is
      `:bad_header`, `:bad_checksum`, `:cut_short` or `:no_end_mark` (the log does not end
      with its end mark: cut short, or its last bytes damaged)

  After damage the reader looks for the next whole frame (header and payload checksums both
  holding) and goes on from there; a random match needs both CRC-32s to agree by chance.
  """

  @magic "VJ"
  @record 1
  @end_mark ?E
  @overhead 15

  @doc "The frame of a record."
  @spec record(term) :: binary
  def record(term), do: frame(@record, :erlang.term_to_binary(term))

  @doc "The end mark, written after every append."
  @spec end_mark() :: binary
  def end_mark, do: frame(@end_mark, "")

  @doc false
  @spec frame(0..255, binary) :: binary
  def frame(kind, payload) do
    head = <<@magic::binary, kind, byte_size(payload)::32>>
    <<head::binary, :erlang.crc32(head)::32, payload::binary, :erlang.crc32(payload)::32>>
  end

  @type item ::
          {:record, non_neg_integer, binary}
          | {:kind, non_neg_integer, byte}
          | {:damaged, non_neg_integer, :bad_header | :bad_checksum | :cut_short | :no_end_mark}

  @doc "The items of a log (see the moduledoc); the end mark is checked, not listed."
  @spec parse(binary) :: [item]
  def parse(bin) when is_binary(bin), do: parse(bin, 0, [], false)

  defp parse(bin, off, acc, ended?) when off >= byte_size(bin) do
    if ended?, do: Enum.reverse(acc), else: Enum.reverse([{:damaged, off, :no_end_mark} | acc])
  end

  defp parse(bin, off, acc, _ended?) do
    case frame_at(bin, off) do
      {:ok, @end_mark, "", next} ->
        parse(bin, next, acc, next == byte_size(bin))

      {:ok, @record, payload, next} ->
        parse(bin, next, [{:record, off, payload} | acc], false)

      {:ok, kind, _payload, next} ->
        parse(bin, next, [{:kind, off, kind} | acc], false)

      {:bad_checksum, next} ->
        parse(bin, next, [{:damaged, off, :bad_checksum} | acc], false)

      :cut_short ->
        Enum.reverse([{:damaged, off, :cut_short} | acc])

      :bad_header ->
        case next_frame(bin, off + 1) do
          nil -> Enum.reverse([{:damaged, off, :bad_header} | acc])
          next -> parse(bin, next, [{:damaged, off, :bad_header} | acc], false)
        end
    end
  end

  # The frame at `off`: {:ok, kind, payload, next offset}, {:bad_checksum, next offset} (the
  # header holds, so its length can be trusted), :cut_short (a good header, the frame runs past
  # the end) or :bad_header.
  defp frame_at(bin, off) do
    case bin do
      <<_::binary-size(off), @magic, kind, len::32, hcrc::32, rest::binary>> ->
        cond do
          :erlang.crc32(<<@magic::binary, kind, len::32>>) != hcrc ->
            :bad_header

          byte_size(rest) < len + 4 ->
            :cut_short

          true ->
            <<payload::binary-size(len), pcrc::32, _::binary>> = rest

            if :erlang.crc32(payload) == pcrc,
              do: {:ok, kind, payload, off + @overhead + len},
              else: {:bad_checksum, off + @overhead + len}
        end

      <<_::binary-size(off), tail::binary>> ->
        # fewer bytes than a header: the start of a frame cut short, or something else
        if byte_size(tail) < @overhead - 4 and
             binary_part(@magic, 0, min(2, byte_size(tail))) ==
               binary_part(tail, 0, min(2, byte_size(tail))),
           do: :cut_short,
           else: :bad_header
    end
  end

  # the next offset from `from` where a whole frame starts (both checksums hold)
  defp next_frame(bin, from) when from >= byte_size(bin), do: nil

  defp next_frame(bin, from) do
    case :binary.match(bin, @magic, scope: {from, byte_size(bin) - from}) do
      :nomatch ->
        nil

      {at, _} ->
        case frame_at(bin, at) do
          {:ok, _kind, _payload, _next} -> at
          _ -> next_frame(bin, at + 1)
        end
    end
  end
end
