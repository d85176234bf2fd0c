defmodule Vws.Links.VAL.Error do
  @moduledoc """
  A VAL data message that could not be decoded or built (PROTOCOLS.md §3 "VAL data message").
  Returned as `{:error, %Vws.Links.VAL.Error{}}` by `Vws.Links.VAL.Message.decode/1` and
  `Vws.Links.VAL.Message.new/4`, never raised by them.

  Reasons:

    * `:too_short` — fewer than the three header bytes (LUN, function, qualifier).
    * `:bad_lun` — a LUN above 5 (the supervisory system has LUNs 0–5); `value` holds it.
    * `:bad_function` — a function code other than 1 WRITE, 2 READ, 3 REPLY; `value` holds it.
    * `:bad_qualifier` — a qualifier outside 0–255, or a LUN 3 message code name we do not know.
    * `:too_long` — more than 256 bytes of message text; `value` holds the length.
    * `:not_ascii` — a text byte above 0x7F; `value` holds its offset in the text.
  """

  defexception [:reason, :value]

  @type reason :: :too_short | :bad_lun | :bad_function | :bad_qualifier | :too_long | :not_ascii
  @type t :: %__MODULE__{reason: reason, value: term}

  @impl true
  def message(%__MODULE__{reason: :too_short}),
    do: "VAL data message shorter than its 3-byte header (LUN, function, qualifier)"

  def message(%__MODULE__{reason: :bad_lun, value: v}),
    do: "VAL data message for logical unit #{inspect(v)}; only LUNs 0-5 exist"

  def message(%__MODULE__{reason: :bad_function, value: v}),
    do: "VAL data message with function code #{inspect(v)}; expected 1 WRITE, 2 READ or 3 REPLY"

  def message(%__MODULE__{reason: :bad_qualifier, value: v}),
    do: "VAL data message qualifier #{inspect(v)} is not a byte or a known LUN 3 message code"

  def message(%__MODULE__{reason: :too_long, value: n}),
    do: "VAL message text is #{n} bytes long; at most 256 fit in one data message"

  def message(%__MODULE__{reason: :not_ascii, value: at}),
    do: "VAL message text has a non-ASCII byte at offset #{at}; the monitor speaks 7-bit ASCII"

  def message(%__MODULE__{reason: reason}), do: "VAL data message error #{inspect(reason)}"
end
