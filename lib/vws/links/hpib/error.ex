defmodule Vws.Links.HPIB.Error do
  @moduledoc """
  Why an HPIB request did not get its answer. Returned as `{:error, %Vws.Links.HPIB.Error{}}` by
  `Vws.Links.HPIB.query/4`, `write/4`, `transaction/4` and `check_response/2`; never raised by them.
  `address` is the device's primary address, `detail` adds what is known.

  Reasons:

    * `:timeout` — the device did not answer within the request's time. The connection is then
      closed and opened again, so a late answer can never be taken for the answer to a later
      request (`detail`: the milliseconds allowed).
    * `:not_connected` — the device's endpoint is not connected (refused, unreachable, or
      reconnecting after a failure); requests fail at once instead of waiting (`detail`: the
      last connection error).
    * `:closed` — the connection was lost while the request waited for its answer.
    * `:send_failed` — the bytes could not be written (`detail`: the transport's reason).
    * `:bad_response` — an answer came but does not answer the query (`detail`: the
      `Vws.Codecs.SCPI.Error`).
    * `:no_device` — no device process at that address on that bus (not configured, or
      restarting).
  """

  defexception [:reason, :address, :detail]

  @type reason :: :timeout | :not_connected | :closed | :send_failed | :bad_response | :no_device
  @type t :: %__MODULE__{reason: reason, address: non_neg_integer | nil, detail: term}

  @impl true
  def message(%__MODULE__{reason: :timeout, address: a, detail: ms}),
    do: "HPIB device #{a} did not answer within #{ms} ms"

  def message(%__MODULE__{reason: :not_connected, address: a, detail: why}),
    do: "HPIB device #{a} is not connected#{because(why)}"

  def message(%__MODULE__{reason: :closed, address: a}),
    do: "the connection to HPIB device #{a} was lost while waiting for its answer"

  def message(%__MODULE__{reason: :send_failed, address: a, detail: why}),
    do: "could not send to HPIB device #{a}#{because(why)}"

  def message(%__MODULE__{reason: :bad_response, address: a, detail: detail}) do
    what = if is_exception(detail), do: ": " <> Exception.message(detail), else: ""
    "HPIB device #{a} answered something that is not an answer to the query#{what}"
  end

  def message(%__MODULE__{reason: :no_device, address: a}),
    do: "no HPIB device is configured at address #{a} (or it is restarting)"

  def message(%__MODULE__{reason: reason, address: a}),
    do: "HPIB device #{a}: #{inspect(reason)}"

  defp because(nil), do: ""
  defp because(why), do: " (#{inspect(why)})"

  @doc """
  The error as a command status or device status shows it, naming the instrument:

      iex> Vws.Links.HPIB.Error.status_reason(%Vws.Links.HPIB.Error{reason: :timeout, detail: 500}, "DAQ #1")
      "DAQ #1 NOT ANSWERING (NO ANSWER IN 500 MS)"
  """
  @spec status_reason(t, String.t()) :: String.t()
  def status_reason(%__MODULE__{reason: :timeout, detail: ms}, device),
    do: "#{device} NOT ANSWERING (NO ANSWER IN #{ms} MS)"

  # the connection was dropped because the instrument did not answer, and is being made again
  def status_reason(%__MODULE__{reason: :not_connected, detail: :timeout}, device),
    do: "#{device} NOT ANSWERING (TIMED OUT, RECONNECTING)"

  def status_reason(%__MODULE__{reason: :bad_response}, device), do: "#{device} BAD ANSWER"
  def status_reason(%__MODULE__{reason: :closed}, device), do: "#{device} CONNECTION LOST"
  def status_reason(%__MODULE__{reason: :no_device}, device), do: "NO LINK TO #{device}"
  def status_reason(%__MODULE__{}, device), do: "#{device} NOT CONNECTED"
end
