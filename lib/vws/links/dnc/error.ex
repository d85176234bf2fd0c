defmodule Vws.Links.DNC.Error do
  @moduledoc """
  A problem found while decoding the GE-2000 DNC Level 2 link (PROTOCOLS.md §2).

  `Vws.Links.DNC.Frame.feed/2` returns these as `{:error, %Vws.Links.DNC.Error{}}` among the frames; decoding
  always goes on. `byte` is the offending byte where there is one, else `nil`. Reasons:

    * `:bad_bcc` — a complete block whose block check (LRC or CRC-16) does not match: it was damaged
      on the line. The receiver answers NAK and the sender retransmits.
    * `:too_long` — a block's text ran past `max_text` bytes without an ETX. The rest of the block is
      discarded up to its ETX and BCC, or up to the next SOH, STX, ENQ, EOT, NAK or DLE.
    * `:malformed` — a block or a DLE sequence was broken off by a byte that cannot stand there (a
      header character other than `S`/`R`, `N`/`C`, an operation letter and STX; a control character
      inside text; DLE followed by something other than `0`, `1` or `;`). Decoding resumes at that byte.
    * `:unexpected_byte` — a byte that starts nothing, between blocks. Reported once per run of such
      bytes; the rest of the run is skipped silently.
  """

  @type reason :: :bad_bcc | :too_long | :malformed | :unexpected_byte
  @type t :: %__MODULE__{reason: reason, byte: byte | nil}

  defexception [:reason, :byte]

  @impl true
  def message(%__MODULE__{reason: :bad_bcc}) do
    "block check (LRC/CRC) mismatch: the block was damaged on the line; answer NAK so the sender retransmits"
  end

  def message(%__MODULE__{reason: :too_long}) do
    "block text longer than the configured maximum: block discarded (peer's block size or line noise?)"
  end

  def message(%__MODULE__{reason: :malformed, byte: byte}) do
    "malformed block or DLE sequence, broken off by byte #{hex(byte)}: block discarded"
  end

  def message(%__MODULE__{reason: :unexpected_byte, byte: byte}) do
    "unexpected byte #{hex(byte)} between blocks: skipped up to the next control character " <>
      "(line noise, or wrong baud rate/framing?)"
  end

  def message(%__MODULE__{reason: reason}), do: "DNC link error: #{inspect(reason)}"

  defp hex(nil), do: "(none)"
  defp hex(byte), do: "0x" <> String.pad_leading(Integer.to_string(byte, 16), 2, "0")
end
