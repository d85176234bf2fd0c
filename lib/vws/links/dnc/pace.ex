defmodule Vws.Links.DNC.Pace do
  @moduledoc """
  When a drip feed's sender asks again after a WACK (ours, docs/dnc-drip-feed.md "At the
  machine's pace"): learned from the machine instead of a fixed `wack_delay`. Pure data, kept in
  the transmission's record (`Vws.Links.DNC.Transfer`) by `Vws.Links.DNC.Session`.

  X3.28 gives the receiver one word for "taken, no room": WACK; the sender may only ask again
  with ENQ, and the answer is WACK (still no room) or the block's acknowledgement (room again).
  So the sender measures what it can see: between two moments the machine had room again (an
  acknowledgement after a WACK) its buffer went from "one block short" to "one block short", so
  the text sent between them is what the machine ran — the **consumption rate**, averaged
  (`released/3`). The next ENQ goes when the machine has run about one block at that rate
  (`wait/3`): earlier, it costs one ENQ and one WACK on the line (four characters); later, the
  buffer runs a little lower, never dry while it holds more than a few blocks.

  Before a rate is known (the first pauses of a transmission) the wait starts at `@first_probe`
  ms and doubles with each WACK answering our ENQ; a WACK that answers our ENQ with a rate known
  says the rate was too high, and it is lowered. Every wait stays between `@floor` ms and
  `wack_delay` (the limit, 2 s by default, still the longest a sender waits).

  The acknowledgement rules of the session are untouched: this only sets a timer's length, so
  the no-skip/no-repeat guarantees hold as before (`test/vws/links/dnc/session_test.exs`).
  """

  # ms: the first wait of a transmission, and the shortest any wait is
  @first_probe 50
  @floor 20
  # the weight of a new sample in the average rate
  @weight 0.3
  # a WACK answering our ENQ: the rate was too high by at least this much
  @too_early 0.8

  @type t :: %__MODULE__{
          rate: float | nil,
          mark: {integer, non_neg_integer} | nil,
          probe: pos_integer
        }
  defstruct rate: nil, mark: nil, probe: @first_probe

  @doc "A transmission's pace: nothing learned yet."
  @spec new() :: t
  def new, do: %__MODULE__{}

  @doc """
  A WACK came (`again?`: in answer to our ENQ after an earlier one): `{pace, ms}` to wait before
  the ENQ. `limits` gives `max_text` (the room one block needs) and `wack_delay` (the longest).
  """
  @spec wait(t, boolean, map) :: {t, pos_integer}
  def wait(%__MODULE__{rate: nil} = pace, again?, limits) do
    probe = if again?, do: pace.probe * 2, else: pace.probe
    probe = clamp(probe, limits)
    {%{pace | probe: probe}, probe}
  end

  def wait(%__MODULE__{rate: rate} = pace, again?, limits) do
    rate = if again?, do: rate * @too_early, else: rate
    {%{pace | rate: rate}, clamp(ceil(limits.max_text * 1000 / rate), limits)}
  end

  @doc """
  The machine had room again at `now_ms` (an acknowledgement after a WACK), `text_acked` text
  bytes of the transmission taken by then: the rate since the previous such moment is averaged in.
  """
  @spec released(t, integer, non_neg_integer) :: t
  def released(%__MODULE__{mark: {t0, b0}} = pace, now_ms, text_acked)
      when now_ms > t0 and text_acked > b0 do
    sample = (text_acked - b0) * 1000 / (now_ms - t0)
    rate = if pace.rate, do: pace.rate * (1 - @weight) + sample * @weight, else: sample
    %{pace | rate: rate, mark: {now_ms, text_acked}}
  end

  def released(pace, now_ms, text_acked), do: %{pace | mark: {now_ms, text_acked}}

  @doc "The consumption rate learned, text bytes a second (nil before two pauses)."
  @spec rate(t) :: float | nil
  def rate(%__MODULE__{rate: rate}), do: rate

  defp clamp(ms, limits), do: ms |> max(@floor) |> min(max(limits.wack_delay, @floor))
end
