defmodule Vws.Ops.TextTable do
  @moduledoc """
  Rows of words as an aligned text table, for the views printed from iex (`Vws.Ops.Inspect`):
  each column as wide as its widest cell, two spaces between columns, no trailing spaces.

      iex> Vws.Ops.TextTable.render(["ID", "STATE"], [["VWS-1", "idle"], ["VWS-10", "busy"]])
      "ID      STATE\\nVWS-1   idle\\nVWS-10  busy"
  """

  @doc "The header and the rows (lists of strings, as many cells each) as lines of text."
  @spec render([String.t()], [[String.t()]]) :: String.t()
  def render(header, rows) do
    widths =
      Enum.reduce(rows, Enum.map(header, &String.length/1), fn row, widths ->
        Enum.zip_with(row, widths, &max(String.length(&1), &2))
      end)

    Enum.map_join([header | rows], "\n", fn row ->
      row
      |> Enum.zip(widths)
      |> Enum.map_join("  ", fn {cell, w} -> String.pad_trailing(cell, w) end)
      |> String.trim_trailing()
    end)
  end
end
