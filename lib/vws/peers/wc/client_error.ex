defmodule Vws.Peers.WC.ClientError do
  @moduledoc """
  Why a `Vws.Peers.WC.Client` request did not succeed. Returned as `{:error, %Vws.Peers.WC.ClientError{}}`.

  Reasons:

    * `:bad_request` — the request could not be sent: a command letter that is not a command
      set, a set twice in one string, text with `*` or control characters, a program that
      `Vws.Peers.WC.Client.validate_program/1` rejects; `data` says what.
    * `:nak` — the CEC answered `E` to every try of a string; `data` is
      `%{sequence: n, tries: n}`.
    * `:timeout` — no reply to a string within the reply timeout, on every try; `data` is
      `%{sequence: n, tries: n}`.
    * `:closed` — the link to SUN_COMM is closed and could not be opened again.
    * `:command_failed` — a command's status came back other than `DONE`; `data` is
      `%{set: name, number: n, status: "ERROR …"}`. This is the CEC's own reason, word for word.
    * `:command_timeout` — a command did not reach `DONE` (or its number never appeared) within
      the time given; `data` is `%{set: name, number: n, last: last status text, ms: timeout}`.
    * `:bad_status` — a command-status answer was not `cccc` + a word; `data` is the text.
    * `:transfer_failed` — an NC program transfer broke off; `data` is
      `%{direction: :download | :upload, line: n, why: text}`. The client then drops and reopens
      the link so that SUN_COMM abandons the transfer (its Monarch command ends `ERROR`).
    * `:program_crc` — every line of an NC program transfer was answered, but the whole
      program is not the same at both ends (PROTOCOLS.md §1 "Whole-program check"): the CRC
      of the program as its sender has it (`sent`) is not the CRC of what its receiver took
      (`stored`); `data` is `%{direction: :download | :upload, number: n, sent: crc, stored:
      crc}`. After a download the CEC keeps its old NC file (its command ends
      `ERROR PROGRAM CRC …`); after an upload the lines received are not returned.

      iex> Exception.message(%Vws.Peers.WC.ClientError{reason: :command_failed,
      ...>   data: %{set: "ROBOT", number: 9, status: "ERROR NO LINK TO VAL II"}})
      "ROBOT command 0009 ended ERROR NO LINK TO VAL II"
  """

  defexception [:reason, :data]

  @type reason ::
          :bad_request
          | :nak
          | :timeout
          | :closed
          | :command_failed
          | :command_timeout
          | :bad_status
          | :transfer_failed
          | :program_crc

  @type t :: %__MODULE__{reason: reason, data: term}

  @impl true
  def message(%__MODULE__{reason: :bad_request, data: why}), do: "request not sent: #{why}"

  def message(%__MODULE__{reason: :nak, data: %{sequence: seq, tries: tries}}),
    do: "the CEC answered E (bad block check) to all #{tries} tries of string #{number(seq)}"

  def message(%__MODULE__{reason: :timeout, data: %{sequence: seq, tries: tries}}),
    do: "no reply from the CEC to string #{number(seq)} after #{tries} tries"

  def message(%__MODULE__{reason: :closed}),
    do: "the link to the CEC (SUN_COMM) is closed and could not be opened again"

  def message(%__MODULE__{reason: :command_failed, data: %{set: set, number: n, status: status}}),
    do: "#{set} command #{number(n)} ended #{status}"

  def message(%__MODULE__{reason: :command_timeout, data: %{set: set, number: n} = d}) do
    "#{set} command #{number(n)} was not DONE within #{d.ms} ms; last status answer #{inspect(d.last)}"
  end

  def message(%__MODULE__{reason: :bad_status, data: text}),
    do: "the command-status answer #{inspect(text)} is not a command number and a word"

  def message(%__MODULE__{reason: :transfer_failed, data: %{direction: dir, line: n, why: why}}),
    do: "NC program #{dir} broke off at line #{n}: #{why}"

  def message(%__MODULE__{reason: :program_crc, data: %{direction: :download} = d}),
    do:
      "NC program download (MONARCH command #{number(d.number)}): the CEC took a program " <>
        "with CRC #{crc(d.stored)}, not the one sent (CRC #{crc(d.sent)}); it is not stored"

  def message(%__MODULE__{reason: :program_crc, data: %{direction: :upload} = d}),
    do:
      "NC program upload (MONARCH command #{number(d.number)}): the program received has " <>
        "CRC #{crc(d.stored)}, the CEC sent one with CRC #{crc(d.sent)}; it is not kept"

  def message(%__MODULE__{reason: reason, data: data}),
    do: "WC client error #{inspect(reason)}: #{inspect(data)}"

  defp number(n) when is_integer(n), do: Vws.Codecs.WC.Command.pad4(n)
  defp number(n), do: inspect(n)

  defp crc(c), do: Vws.Codecs.WC.ProgramCRC.format(c)
end
