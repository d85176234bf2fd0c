defmodule Vws.Codecs.WC.Words do
  @moduledoc """
  What the WC reads after `ERROR `: upper-case words and numbers, never an Elixir term
  (PROTOCOLS.md §1: a status text is what a person at the WC reads, at most 94 characters).

  The one place a reason that is not already text — an atom, an exception, `{:error, term}`, a
  file error — becomes a status text; whoever has the raw term logs it. Pure.

      iex> Vws.Codecs.WC.Words.of(:bad_directory)
      "BAD DIRECTORY"
      iex> Vws.Codecs.WC.Words.of({:error, :enospc})
      "ENOSPC"
      iex> Vws.Codecs.WC.Words.of(%{a: 1})
      "INTERNAL FAULT"
      iex> Vws.Codecs.WC.Words.text?("ERROR VISE FORCE 310 N BELOW 800 N")
      true
      iex> Vws.Codecs.WC.Words.text?("ERROR BAD RESULT {:error, :bad_directory}")
      false
  """

  # what a status text may hold: upper-case letters, digits, blanks and the punctuation the
  # seed's and our texts use (`DAQ #1`, `(…)`, `1.5`, `-301`, `TRAY1/50`, `%`, `:` of a time)
  # (\z, not $: $ also matches before a final newline, and "LOST\n" is no status text — a reason
  # ending in a newline was taken as words, and SUN_COMM crashed framing "ERROR LOST\n")
  @allowed ~r/\A[A-Z0-9 #().,:;?!*\/%+\-=<>_']*\z/

  @doc "True when `text` is a status text a WC may be shown (see the moduledoc)."
  @spec text?(String.t()) :: boolean
  def text?(text) when is_binary(text), do: text =~ @allowed

  @doc "Any reason as upper-case words and numbers (see the moduledoc)."
  @spec of(term) :: String.t()
  def of(reason), do: reason |> words() |> clean()

  defp words({:error, reason}), do: words(reason)
  defp words(%{__exception__: true} = e), do: Exception.message(e)
  defp words(text) when is_binary(text), do: text
  defp words(atom) when is_atom(atom), do: atom |> Atom.to_string() |> String.replace("_", " ")
  defp words(n) when is_integer(n), do: Integer.to_string(n)
  defp words(n) when is_float(n), do: :erlang.float_to_binary(n, [:compact, decimals: 3])

  defp words(tuple) when is_tuple(tuple) and tuple_size(tuple) <= 4,
    do: tuple |> Tuple.to_list() |> Enum.map_join(" ", &words/1)

  defp words(list) when is_list(list) and length(list) <= 4 do
    if List.ascii_printable?(list),
      do: List.to_string(list),
      else: Enum.map_join(list, " ", &words/1)
  end

  defp words(_other), do: "INTERNAL FAULT"

  defp clean(text) do
    text
    |> String.upcase()
    |> String.replace(~r/[^A-Z0-9 #().,:;?!*\/%+\-=<>_']/, " ")
    |> String.replace(~r/\s+/, " ")
    |> String.trim()
    |> String.slice(0, 80)
    |> case do
      "" -> "INTERNAL FAULT"
      words -> words
    end
  end
end
