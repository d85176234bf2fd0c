defmodule Vws.Links.DNC.Progress do
  @moduledoc """
  The progress of the transfer under way on a DNC link, as `Vws.Links.DNC.info/1` shows it under
  `transfer` and `Vws.Links.DNC.progress/1` returns it (nil when nothing is transferred):

    * `direction` — `:out` (this end sends) or `:in`; `command` — the command block
      (`%Vws.Links.DNC.Frame.Command{}`, nil for text without a command); `program` — the file it names
      (its text, trimmed; nil when it names none)
    * `blocks`, `total_blocks` — blocks acknowledged so far and in all; `bytes`, `total_bytes` —
      their bytes on the line (a reception: its text); `program_bytes`, `total_program_bytes` —
      the program's text bytes (the totals of a reception are nil: not known before its end)
    * `retries` — NAKs, ENQs and copies in this transfer so far; `pauses` — WACKs, the receiver
      asking the sender to wait (flow control, not a fault)
    * `started_ms` (monotonic ms), `elapsed_ms`, `chars_per_s` (bytes a second so far) and
      `eta_s` (seconds left at that rate; nil when the total or the rate is unknown)

  Pure: computed from a `Vws.Links.DNC.Session` and the time.
  """

  alias Vws.Links.DNC.Session

  @doc "The progress of `session`'s transfer at `now` (monotonic native units), or nil."
  @spec of(Session.t(), integer) :: map | nil
  def of(session, now) do
    case Session.transfer(session) do
      nil -> nil
      t -> describe(t, now)
    end
  end

  @doc "The progress of a `Vws.Links.DNC.Session.transfer/1` at `now`."
  @spec describe(map, integer) :: map
  def describe(t, now) do
    started_ms = System.convert_time_unit(t.started, :native, :millisecond)
    elapsed = max(System.convert_time_unit(now - t.started, :native, :millisecond), 1)
    rate = t.bytes * 1000 / elapsed

    eta =
      cond do
        t.total_bytes == nil -> nil
        t.bytes >= t.total_bytes -> 0.0
        rate > 0 -> Float.round((t.total_bytes - t.bytes) / rate, 1)
        true -> nil
      end

    %{
      direction: t.direction,
      command: t.command,
      program: program(t.command),
      blocks: t.blocks,
      total_blocks: t.total_blocks,
      bytes: t.bytes,
      total_bytes: t.total_bytes,
      program_bytes: t.program_bytes,
      total_program_bytes: t.total_program_bytes,
      retries: t.retries,
      pauses: Map.get(t, :pauses, 0),
      started_ms: started_ms,
      elapsed_ms: elapsed,
      chars_per_s: round(rate),
      eta_s: eta
    }
  end

  # (a remote request's nnnnnn.PRO/v names the file nnnnnn.PRO)
  defp program(%{text: text}) when is_binary(text) do
    case text |> String.split("/") |> hd() |> String.trim() do
      "" -> nil
      name -> name
    end
  end

  defp program(_command), do: nil
end
