defmodule Vws.Links.DNC.LinkError do
  @moduledoc """
  Why a DNC Level 2 transmission did not complete (PROTOCOLS.md §2, "Errors").

  `Vws.Links.DNC.request/4` returns `{:error, %Vws.Links.DNC.LinkError{}}`. A transmission either completes
  with every block acknowledged or ends with one of these; nothing is ever half-delivered as if it
  were whole. `block` is the number of the block concerned (1 = the command block of a request,
  then its text blocks) and `count` the number of tries, where they apply. Reasons:

    * `:link_down` — no connection to the peer (never connected, or lost during the transmission).
    * `:no_answer_to_bid` — our ENQ was not answered ACK0 after `count` bids.
    * `:contention` — the peer kept bidding over ours `count` times (we yield each time).
    * `:nak_limit` — block `block` was refused (NAK, or lost and asked for again) `count` times.
    * `:no_reply` — block `block` got no valid reply, even after `count` ENQs.
    * `:wack_limit` — the peer answered WACK (busy) `count` times running.
    * `:aborted` — the peer sent EOT in the middle of our transmission, at block `block`.
    * `:no_response` — after our `R` command the peer did not bid to send its answer in time.
    * `:receive_timeout` — while receiving, the peer stopped sending after `count` blocks.
    * `:too_large` — the peer's answer grew past the link's `max_receive` bytes.
    * `:timeout` — the caller's deadline passed before the transmission ended.
    * `:invalid_text` — a text block holds a transmission control or is over `max_text` bytes.
  """

  @type reason ::
          :link_down
          | :no_answer_to_bid
          | :contention
          | :nak_limit
          | :no_reply
          | :wack_limit
          | :aborted
          | :no_response
          | :receive_timeout
          | :too_large
          | :timeout
          | :invalid_text
  @type t :: %__MODULE__{reason: reason, block: non_neg_integer | nil, count: integer | nil}

  defexception [:reason, :block, :count]

  @impl true
  def message(%__MODULE__{reason: :link_down}),
    do: "no connection to the DNC peer: check the cable, the endpoint and that the machine is on"

  def message(%__MODULE__{reason: :no_answer_to_bid, count: n}),
    do: "the DNC peer did not answer our bid (ENQ) #{n} times: is it in DNC Level 2 mode?"

  def message(%__MODULE__{reason: :contention, count: n}),
    do: "the DNC peer bid over ours #{n} times running; the link is too busy"

  def message(%__MODULE__{reason: :nak_limit, block: b, count: n}),
    do: "block #{b} was rejected #{n} times (bad block check): line noise or wrong line settings"

  def message(%__MODULE__{reason: :no_reply, block: b, count: n}),
    do: "no reply to block #{b} even after #{n} ENQs: the peer stopped answering"

  def message(%__MODULE__{reason: :wack_limit, count: n}),
    do: "the peer answered busy (WACK) #{n} times running and never became ready"

  def message(%__MODULE__{reason: :aborted, block: b}),
    do: "the peer ended the transmission (EOT) at block #{b}"

  def message(%__MODULE__{reason: :no_response}),
    do: "after our R command the peer never bid to send its answer"

  def message(%__MODULE__{reason: :receive_timeout, count: n}),
    do: "the peer stopped sending after #{n} blocks"

  def message(%__MODULE__{reason: :too_large, count: n}),
    do: "the peer's answer is larger than the #{n} bytes this link accepts"

  def message(%__MODULE__{reason: :timeout}),
    do: "the request's deadline passed before the transmission ended"

  def message(%__MODULE__{reason: :invalid_text}),
    do: "a text block holds a transmission control character or is longer than the block size"

  def message(%__MODULE__{reason: reason}), do: "DNC link error #{inspect(reason)}"

  @doc """
  The error as the words of an `ERROR <reason>` command status (upper case, no punctuation the
  WC link forbids).

      iex> Vws.Links.DNC.LinkError.status_text(%Vws.Links.DNC.LinkError{reason: :no_reply, block: 3, count: 3})
      "DNC NO REPLY TO BLOCK 3 AFTER 3 ENQ"
  """
  @spec status_text(t) :: String.t()
  def status_text(%__MODULE__{reason: reason, block: b, count: n}) do
    case reason do
      :link_down -> "DNC LINK DOWN"
      :no_answer_to_bid -> "DNC NO ANSWER TO BID AFTER #{n} ENQ"
      :contention -> "DNC BID CONTENTION #{n} TIMES"
      :nak_limit -> "DNC BLOCK #{b} REJECTED #{n} TIMES"
      :no_reply -> "DNC NO REPLY TO BLOCK #{b} AFTER #{n} ENQ"
      :wack_limit -> "DNC PEER BUSY (WACK) #{n} TIMES"
      :aborted -> "DNC TRANSMISSION ABORTED BY PEER AT BLOCK #{b}"
      :no_response -> "DNC NO RESPONSE TO R COMMAND"
      :receive_timeout -> "DNC PEER STOPPED SENDING AFTER #{n} BLOCKS"
      :too_large -> "DNC ANSWER OVER #{n} BYTES"
      :timeout -> "DNC REQUEST TIMEOUT"
      :invalid_text -> "DNC TEXT NOT SENDABLE"
      other -> "DNC " <> unknown_reason(other)
    end
  end

  # a reason this module does not know, in upper-case words (never an Elixir term)
  defp unknown_reason(reason) when is_atom(reason) do
    case reason |> Atom.to_string() |> String.upcase() |> String.replace(~r/[^A-Z0-9]+/, " ") do
      " " -> "LINK ERROR"
      "" -> "LINK ERROR"
      words -> String.trim(words)
    end
  end

  defp unknown_reason(_reason), do: "LINK ERROR"
end
