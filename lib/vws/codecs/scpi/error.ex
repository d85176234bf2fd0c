defmodule Vws.Codecs.SCPI.Error do
  @moduledoc """
  A line `Vws.Codecs.SCPI` could not accept (PROTOCOLS.md §4). Returned as `{:error, %Vws.Codecs.SCPI.Error{}}`
  by `Vws.Codecs.SCPI.decode_command/1`, `Vws.Codecs.SCPI.decode_response/2` and `Vws.Codecs.SCPI.feed/2`; never
  raised by them. `line` holds the offending text (cut to 80 bytes) when there is one.

  Reasons:

    * `:line_too_long` — a line grew past the decoder's `max_line` bytes before its LF; it was
      discarded up to and including its LF (`max` is set).
    * `:empty` — a blank line.
    * `:bad_character` — a byte that is not printable ASCII (or tab) in a line.
    * `:undefined_header` — the command's header is not one of the subset.
    * `:missing_parameter` — a command that needs a channel list came without one.
    * `:unexpected_parameter` — a command that takes no parameter came with one.
    * `:bad_channel_list` — the parameter is not a channel list `(@101:116)` / `(@101,105)`.
    * `:channel_out_of_range` — a channel is not slot digit 1–9 plus channel 01–99, or a range
      runs backwards or across slots.
    * `:bad_response` — a response line does not have the shape its query asks for: a reading
      that is no number, a count of readings other than the channels asked, a state not 0/1, …
    * `:no_response` — `decode_response/2` was asked about a command that has no response.

  `scpi_error/1` gives the SCPI error-queue entry an instrument would log for a bad command.
  """

  defexception [:reason, :line, :max]

  @type reason ::
          :line_too_long
          | :empty
          | :bad_character
          | :undefined_header
          | :missing_parameter
          | :unexpected_parameter
          | :bad_channel_list
          | :channel_out_of_range
          | :bad_response
          | :no_response

  @type t :: %__MODULE__{reason: reason, line: binary | nil, max: pos_integer | nil}

  @queue_entries %{
    line_too_long: {-363, "Input buffer overrun"},
    empty: {-100, "Command error"},
    bad_character: {-101, "Invalid character"},
    undefined_header: {-113, "Undefined header"},
    missing_parameter: {-109, "Missing parameter"},
    unexpected_parameter: {-108, "Parameter not allowed"},
    bad_channel_list: {-102, "Syntax error"},
    channel_out_of_range: {-222, "Data out of range"},
    bad_response: {-100, "Command error"},
    no_response: {-100, "Command error"}
  }

  @doc """
  The SCPI error-queue entry (code, text) for this error, as `SYST:ERR?` reports it.

      iex> Vws.Codecs.SCPI.Error.scpi_error(%Vws.Codecs.SCPI.Error{reason: :undefined_header})
      {-113, "Undefined header"}
  """
  @spec scpi_error(t) :: {integer, String.t()}
  def scpi_error(%__MODULE__{reason: reason}),
    do: Map.get(@queue_entries, reason, {-100, "Command error"})

  @impl true
  def message(%__MODULE__{reason: :line_too_long, max: max}),
    do: "SCPI line longer than #{max} bytes without a line feed; it was discarded"

  def message(%__MODULE__{reason: :empty}), do: "empty SCPI line"

  def message(%__MODULE__{reason: :bad_character, line: line}),
    do: "SCPI line #{inspect(line)} contains a byte that is not printable ASCII"

  def message(%__MODULE__{reason: :undefined_header, line: line}),
    do: "SCPI command #{inspect(line)} is not one this instrument knows"

  def message(%__MODULE__{reason: :missing_parameter, line: line}),
    do: "SCPI command #{inspect(line)} needs a channel list such as (@101:116)"

  def message(%__MODULE__{reason: :unexpected_parameter, line: line}),
    do: "SCPI command #{inspect(line)} takes no parameter"

  def message(%__MODULE__{reason: :bad_channel_list, line: line}),
    do:
      "SCPI command #{inspect(line)} has a malformed channel list; write (@101:116) or (@101,105)"

  def message(%__MODULE__{reason: :channel_out_of_range, line: line}),
    do:
      "SCPI command #{inspect(line)} names a channel that does not exist " <>
        "(three digits: slot 1-9, channel 01-99; ranges ascending within one slot)"

  def message(%__MODULE__{reason: :bad_response, line: line}),
    do: "instrument response #{inspect(line)} does not answer the query that was sent"

  def message(%__MODULE__{reason: :no_response}),
    do: "this SCPI command has no response to decode"

  def message(%__MODULE__{reason: reason}), do: "SCPI error #{inspect(reason)}"
end
