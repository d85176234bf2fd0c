defmodule Vws.Test.Serial do
  @moduledoc """
  Shared by the serial tests (issue 28: RS-232 profile, RFC 2217): NC programs of a given size,
  bytes cut at given points, and a Monarch command run to its end from a raw WC peer.
  """

  alias Vws.Test.WCPeer

  @doc "The lines of an NC program of at least `bytes` bytes of short blocks, `number` (O4711)."
  def program_lines(bytes, number \\ "O4711") do
    body =
      for i <- 1..(div(bytes, 22) + 1),
          do: "N#{i} G01 X#{rem(i * 37, 1000)}.#{rem(i, 10)} F300"

    ["%", number] ++ body ++ ["M30", "%"]
  end

  @doc "The same program as DNC text (LF lines)."
  def program_text(bytes, number \\ "O4711"),
    do: Vws.Links.DNC.Program.to_text(program_lines(bytes, number))

  @doc "`bin` cut at the given points (each taken modulo its size + 1), in order."
  def split(bin, cuts) do
    cuts = cuts |> Enum.map(&rem(&1, byte_size(bin) + 1)) |> Enum.sort() |> Enum.uniq()

    {pieces, _at, rest} =
      Enum.reduce(cuts, {[], 0, bin}, fn cut, {acc, at, rest} ->
        <<piece::binary-size(cut - at), rest::binary>> = rest
        {[piece | acc], cut, rest}
      end)

    Enum.reverse([rest | pieces])
  end

  @doc "Sends Monarch command `number` with `text`; asserts the string's acknowledgement."
  defdelegate send_monarch(peer, number, text), to: Vws.Test.MonarchWC

  @doc "The MONARCH_CMD status once it is no longer EXECUTING."
  def finished(peer, timeout \\ 120_000),
    do:
      WCPeer.await_status(
        peer,
        Vws.Test.MonarchWC.seq(),
        "MONARCH_CMD",
        &(not (&1 =~ "EXECUTING")),
        timeout
      )

  @doc "A Monarch command run to its end: its status (`0001DONE`, `0001ERROR …`)."
  def monarch(peer, number, text) do
    send_monarch(peer, number, text)
    finished(peer)
  end
end
