defmodule Vws.Codecs.WC.Error do
  @moduledoc """
  Why a line on the WC link (PROTOCOLS.md §1) was not accepted. Decoders return it as
  `{:error, %Vws.Codecs.WC.Error{}}`; they never raise on bad input.

  Reasons:

    * `:bad_bcc` — the block check does not match the bytes it covers; `data` is
      `%{computed: 0..255, received: 0..255}`.
    * `:malformed` — the line could not be framed: no `*…*` frame, no three-digit BCC `000`–`255`
      at its end, a string with no command, a reply of unknown form or with a wrong length
      prefix `NN`, or characters outside printable ASCII; `data` is the line.
    * `:bad_sequence` — an intact line whose sequence number is not exactly four digits; `data` is
      the field.
    * `:bad_command` — an intact string with a command that is not an uppercase letter, four
      digits and printable text without `*` (text may be empty only for an `A` command); `data`
      is the command as received.
    * `:line_too_long` — a line longer than the decoder's `max_line`; it was discarded up to its
      LF. `data` is `%{length: bytes_without_terminator, max_line: limit}`.
    * `:text_too_long` — a status text longer than 94 characters, which the two-digit length
      `NN` cannot announce (`Vws.Codecs.WC.Reply.validate/1`); `data` is `%{length: n, max: 94}`.

      iex> Exception.message(%Vws.Codecs.WC.Error{reason: :bad_bcc, data: %{computed: 241, received: 240}})
      "block check mismatch: computed 241, received 240; the sender should resend the line"
  """

  defexception [:reason, :data]

  @type reason ::
          :bad_bcc
          | :malformed
          | :bad_sequence
          | :bad_command
          | :line_too_long
          | :text_too_long

  @type t :: %__MODULE__{reason: reason, data: term}

  @impl true
  def message(%__MODULE__{reason: :bad_bcc, data: %{computed: computed, received: received}}) do
    "block check mismatch: computed #{computed}, received #{received}; " <>
      "the sender should resend the line"
  end

  def message(%__MODULE__{reason: :bad_bcc}),
    do: "block check mismatch; the sender should resend the line"

  def message(%__MODULE__{reason: :malformed, data: data}),
    do: "the line could not be framed as a WC message: #{preview(data)}"

  def message(%__MODULE__{reason: :bad_sequence, data: data}),
    do: "the sequence number must be exactly four digits, got #{preview(data)}"

  def message(%__MODULE__{reason: :bad_command, data: data}) do
    "a command must be an uppercase letter, four digits and printable text without '*', " <>
      "got #{preview(data)}"
  end

  def message(%__MODULE__{reason: :line_too_long, data: %{length: length, max_line: max}}),
    do: "a line of #{length} bytes exceeds the limit of #{max} bytes and was discarded"

  def message(%__MODULE__{reason: :line_too_long}),
    do: "a line exceeded the length limit and was discarded"

  def message(%__MODULE__{reason: :text_too_long, data: %{length: length, max: max}}),
    do: "a status text of #{length} characters exceeds the limit of #{max}"

  def message(%__MODULE__{reason: :text_too_long}),
    do: "a status text exceeds the limit of 94 characters"

  def message(%__MODULE__{reason: reason, data: data}),
    do: "WC link error #{inspect(reason)}: #{inspect(data)}"

  @preview 60
  defp preview(data) when is_binary(data) and byte_size(data) > @preview,
    do: inspect(binary_part(data, 0, @preview)) <> "…"

  defp preview(data), do: inspect(data)
end
