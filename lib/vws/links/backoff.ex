defmodule Vws.Links.Backoff do
  @moduledoc """
  How long a device link waits before it dials its peer again: the one rule of every link that
  dials (`Vws.Links.DDCMP`, `Vws.Links.VAL`, `Vws.Links.DNC`, `Vws.Links.HPIB`), kept by their
  shell, `Vws.Links.Connection`.

  The wait doubles, from `min` up to `max`, each time it is taken — after an attempt that failed
  and after a connection that was lost — and comes back to `min` only when a connection has
  proved itself: the peer answered on it (`reset/1`). A connection that is accepted and then
  dropped without a word proves nothing, so a peer that accepts and drops at once (a terminal
  server whose device is off, a line whose far end is gone) is dialled less and less often, as
  a peer that refuses is — not at a constant rate for ever.

      iex> b = Vws.Links.Backoff.new(100, 500)
      iex> {d1, b} = Vws.Links.Backoff.next(b)
      iex> {d2, b} = Vws.Links.Backoff.next(b)
      iex> {d3, b} = Vws.Links.Backoff.next(b)
      iex> {d4, b} = Vws.Links.Backoff.next(b)
      iex> [d1, d2, d3, d4]
      [100, 200, 400, 500]
      iex> b |> Vws.Links.Backoff.reset() |> Vws.Links.Backoff.next() |> elem(0)
      100
  """

  @enforce_keys [:min, :max, :next]
  defstruct [:min, :max, :next]

  @type t :: %__MODULE__{min: non_neg_integer, max: non_neg_integer, next: non_neg_integer}

  @doc "A backoff whose first wait is `min` ms, doubling up to `max` ms."
  @spec new(non_neg_integer, non_neg_integer) :: t
  def new(min, max) when is_integer(min) and is_integer(max) and min >= 0 and max >= min,
    do: %__MODULE__{min: min, max: max, next: min}

  @doc "The wait to take now, and the backoff with the next wait doubled (at most `max`)."
  @spec next(t) :: {non_neg_integer, t}
  def next(%__MODULE__{next: wait} = b), do: {wait, %{b | next: min(max(wait * 2, 1), b.max)}}

  @doc "The wait `next/1` would give now."
  @spec peek(t) :: non_neg_integer
  def peek(%__MODULE__{next: wait}), do: wait

  @doc "The peer answered: the next wait is `min` again."
  @spec reset(t) :: t
  def reset(%__MODULE__{} = b), do: %{b | next: b.min}
end
