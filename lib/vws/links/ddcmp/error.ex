defmodule Vws.Links.DDCMP.Error do
  @moduledoc """
  A DDCMP message the receiver could not accept (PROTOCOLS.md §3). Returned by
  `Vws.Links.DDCMP.Frame.feed/2` as `{:error, %Vws.Links.DDCMP.Error{}}`, never raised by it.

  Reasons, each with the DDCMP NAK reason the link may answer with:

    * `:header_crc` — a class byte (SOH, ENQ, DLE) was followed by a header whose block check
      failed; the decoder drops one byte and rescans. Reported once per resynchronisation
      episode, not once per byte (NAK reason 1).
    * `:data_crc` — a data message header was good but its data block check failed; the message
      is discarded. `num`, `resp` and `count` come from the (good) header (NAK reason 2).
    * `:too_long` — a data or maintenance header announced more than `max` data bytes; the
      message is skipped without being buffered. `num`, `resp`, `count`, `max` are set (NAK 16).
    * `:header_format` — the header check was good but the header is not a valid message: an
      unknown control TYPE, or a maintenance message whose fill bytes are not zero. `header`
      holds the six header bytes (NAK reason 17).
  """

  defexception [:reason, :num, :resp, :count, :max, :header]

  @type reason :: :header_crc | :data_crc | :too_long | :header_format

  @type t :: %__MODULE__{
          reason: reason,
          num: 0..255 | nil,
          resp: 0..255 | nil,
          count: non_neg_integer | nil,
          max: non_neg_integer | nil,
          header: binary | nil
        }

  @impl true
  def message(%__MODULE__{reason: :header_crc}) do
    "DDCMP header failed its block check (CRC); bytes were dropped until the next good header"
  end

  def message(%__MODULE__{reason: :data_crc, num: num}) do
    "DDCMP data message #{num} failed its data block check (CRC) and was discarded; " <>
      "the sender should retransmit it"
  end

  def message(%__MODULE__{reason: :too_long, num: num, count: count, max: max}) do
    "DDCMP message #{num} carries #{count} data bytes, more than the receive limit of " <>
      "#{max}; it was skipped (raise :max_data or shorten the peer's messages)"
  end

  def message(%__MODULE__{reason: :header_format, header: header}) do
    "DDCMP header has a good block check but an invalid format " <>
      "(header bytes #{inspect(header, base: :hex)}); it was skipped"
  end

  def message(%__MODULE__{reason: reason}), do: "DDCMP receive error #{inspect(reason)}"
end
