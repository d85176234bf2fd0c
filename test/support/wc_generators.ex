defmodule Vws.Codecs.WC.Generators do
  @moduledoc false
  # PropEr generators for the WC link codec tests (PROTOCOLS.md §1).

  import :proper_types,
    only: [
      bind: 3,
      elements: 1,
      exactly: 1,
      list: 1,
      non_empty: 1,
      oneof: 1,
      range: 2,
      resize: 2,
      tuple: 1,
      union: 1
    ]

  alias Vws.Codecs.WC.{Command, CommandString}

  def mode, do: elements([:sum, :xor])

  # Printable ASCII without `*`.
  def command_char, do: union([range(0x20, 0x29), range(0x2B, 0x7E)])

  def printable_char, do: range(0x20, 0x7E)

  # The known sets more often than the other letters.
  def letter, do: union([elements(~c"RMFHGVSA"), range(?A, ?Z)])

  def command do
    bind(
      letter(),
      fn
        ?A -> tuple([exactly(?A), range(0, 9999), resize(20, list(command_char()))])
        l -> tuple([exactly(l), range(0, 9999), resize(20, non_empty(list(command_char())))])
      end,
      false
    )
    |> bind(fn {l, n, chars} -> exactly(Command.new(<<l>>, n, List.to_string(chars))) end, false)
  end

  def command_string do
    bind(
      tuple([range(0, 9999), resize(6, non_empty(list(command())))]),
      fn {seq, commands} -> exactly(%CommandString{sequence: seq, commands: commands}) end,
      false
    )
  end

  def status_text,
    do: bind(resize(94, list(printable_char())), &exactly(List.to_string(&1)), false)

  def line_text, do: bind(resize(60, list(printable_char())), &exactly(List.to_string(&1)), false)

  # Every reply `Vws.Codecs.WC.Reply.decode/2` reads.
  def reply do
    oneof([
      exactly(:nak),
      bind(range(0, 9999), &exactly({:line_ack, &1}), false),
      bind(
        tuple([range(0, 9999), range(0, 0xFFFF)]),
        fn {n, crc} -> exactly({:line_ack, n, crc}) end,
        false
      ),
      bind(range(0, 9999), &exactly({:ack, &1}), false),
      bind(
        tuple([range(0, 9999), status_text()]),
        fn {n, t} -> exactly({:status, n, t}) end,
        false
      )
    ])
  end

  def nc_line,
    do: bind(tuple([range(0, 9999), line_text()]), fn {n, t} -> exactly({:line, n, t}) end, false)

  # Sizes to cut a byte stream at.
  def cuts, do: list(range(1, 40))

  @doc "Cuts `bin` into pieces of the sizes in `sizes`, cycling; the whole binary if none."
  def chunks(bin, []), do: [bin]
  def chunks(bin, sizes), do: do_chunks(bin, sizes, sizes, [])

  defp do_chunks(<<>>, _, _, acc), do: Enum.reverse(acc)
  defp do_chunks(bin, [], all, acc), do: do_chunks(bin, all, all, acc)

  defp do_chunks(bin, [size | rest], all, acc) when byte_size(bin) <= size,
    do: do_chunks(<<>>, rest, all, [bin | acc])

  defp do_chunks(bin, [size | rest], all, acc) do
    <<chunk::binary-size(size), tail::binary>> = bin
    do_chunks(tail, rest, all, [chunk | acc])
  end

  @doc "Feeds `chunks` one by one; returns every item out and the final decoder."
  def feed_all(dec, chunks) do
    {items, dec} =
      Enum.reduce(chunks, {[], dec}, fn chunk, {acc, dec} ->
        {items, dec} = Vws.Codecs.WC.LineDecoder.feed(dec, chunk)
        {[items | acc], dec}
      end)

    {items |> Enum.reverse() |> Enum.concat(), dec}
  end

  @doc "`line` with the byte at `pos` replaced by the `index`-th byte that is not CR, LF or itself."
  def corrupt(line, pos, index) do
    <<before::binary-size(pos), original, rest::binary>> = line
    replacement = Enum.at(Enum.to_list(0..255) -- [original, ?\r, ?\n], index)
    <<before::binary, replacement, rest::binary>>
  end

  @doc "A valid `line`, a position in it and a replacement index for `corrupt/3`."
  def corruption(line), do: tuple([exactly(line), range(0, byte_size(line) - 1), range(0, 252)])
end
