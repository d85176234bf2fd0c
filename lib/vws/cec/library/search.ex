defmodule Vws.CEC.Library.Search do
  @moduledoc """
  Finds library versions by program number, comment and text (`Vws.CEC.Library.search/3`, which
  documents the answer), case-insensitive; pure but for the `read` function it is given.
  """

  @doc "The hits among `programs` (`Vws.CEC.Library.list/1`) for `query` in the fields `where`."
  @spec run([map], String.t(), [:name | :comment | :text], (String.t(), pos_integer -> term)) ::
          [map]
  def run(programs, query, where, read) do
    q = String.downcase(String.trim(query))

    hits =
      for p <- programs, v <- p.versions, q != "" do
        line = if :text in where, do: text_line(read.(v.name, v.version), q)
        comment = String.downcase(Map.get(v, :comment) || "")

        matched =
          [
            :name in where and String.contains?(String.downcase(v.name), q) && :name,
            :comment in where and String.contains?(comment, q) && :comment,
            line && :text
          ]
          |> Enum.filter(& &1)

        %{name: v.name, version: v.version, matched: matched, line: line}
      end

    Enum.reject(hits, &(&1.matched == []))
  end

  defp text_line({:ok, bytes, _v}, q),
    do:
      Enum.find(Vws.Links.DNC.Program.from_text(bytes), &String.contains?(String.downcase(&1), q))

  defp text_line(_unreadable, _q), do: nil
end
