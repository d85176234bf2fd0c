defmodule Vws.Ops.Web.Severity do
  @moduledoc """
  How bad a status or device text is, for the dashboard's colour and its history: the one place
  that decides it (issue 25: not read yet is not an error). Pure; used by `Vws.Ops.Web.State`
  and `Vws.Ops.Web.History`.
  """

  @doc """
  How bad a status or device text is, for the page's colour — the one place that decides it:

    * `"error"` — an `ERROR …` status; `NO DATA` for a reason other than not read yet;
    * `"neutral"` — nothing to say yet: `NONE`, no text, `NO DATA (… NOT READ YET)`, `… NO COMMAND YET`;
    * `"warning"` — `NO DATA` while a link is being (re)connected;
    * `"ok"` — anything else (`DONE`, `EXECUTING`, a device's reading).
  """
  @spec of(String.t() | nil) :: String.t()
  def of(nil), do: "neutral"
  def of("NONE"), do: "neutral"
  def of("ERROR" <> _), do: "error"

  def of("NO DATA" <> why) do
    cond do
      why =~ ~r/NOT READ YET|NO COMMAND YET|NOT YET/ -> "neutral"
      why =~ ~r/CONNECTING|RECONNECTING|STARTING/ -> "warning"
      true -> "error"
    end
  end

  def of(text) when is_binary(text) do
    if text =~ ~r/NOT READ YET|NO COMMAND YET/, do: "neutral", else: "ok"
  end
end
