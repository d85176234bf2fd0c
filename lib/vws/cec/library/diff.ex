defmodule Vws.CEC.Library.Diff do
  @moduledoc """
  Line diffs of NC programs (issue 27), pure: the edit script between two texts' lines
  (`List.myers_difference/2`), what it comes to in a few words (`summary/1`, what `COMPARE_GE`
  tells the WC within its 94 characters), and the script applied (`apply/2`, which the
  properties check: applied to the first text's lines it gives the second's).

      iex> d = Vws.CEC.Library.Diff.lines("%\\nO1\\nX1\\nM30\\n%\\n", "%\\nO1\\nX2\\nM30\\n%\\n")
      iex> Vws.CEC.Library.Diff.summary(d)
      %{removed: 1, added: 1, first_line: 3}
      iex> Vws.CEC.Library.Diff.apply(["%", "O1", "X1", "M30", "%"], d)
      {:ok, ["%", "O1", "X2", "M30", "%"]}
  """

  import Kernel, except: [apply: 2, apply: 3]

  @type t :: [{:eq | :del | :ins, [binary]}]

  @doc "The edit script from text `a`'s lines to text `b`'s (LF ends each line)."
  @spec lines(binary, binary) :: t
  def lines(a, b),
    do:
      List.myers_difference(
        Vws.Links.DNC.Program.from_text(a),
        Vws.Links.DNC.Program.from_text(b)
      )

  @doc """
  Lines removed and added, and the first line of the first text where they differ (1-based;
  nil when they do not).
  """
  @spec summary(t) :: %{
          removed: non_neg_integer,
          added: non_neg_integer,
          first_line: pos_integer | nil
        }
  def summary(diff) do
    {removed, added, first, _at} =
      Enum.reduce(diff, {0, 0, nil, 1}, fn
        {:eq, l}, {r, a, f, at} -> {r, a, f, at + length(l)}
        {:del, l}, {r, a, f, at} -> {r + length(l), a, f || at, at + length(l)}
        {:ins, l}, {r, a, f, at} -> {r, a + length(l), f || at, at}
      end)

    %{removed: removed, added: added, first_line: first}
  end

  @doc """
  Applies the edit script to `lines`: `{:ok, new lines}`, or `:error` when the script's kept and
  removed lines are not `lines` (a script made for another text).
  """
  @spec apply([binary], t) :: {:ok, [binary]} | :error
  def apply(lines, diff), do: apply(lines, diff, [])

  defp apply([], [], acc), do: {:ok, acc |> Enum.reverse() |> Enum.concat()}
  defp apply(lines, [{:ins, l} | rest], acc), do: apply(lines, rest, [l | acc])

  defp apply(lines, [{kind, l} | rest], acc) when kind in [:eq, :del] do
    n = length(l)

    if Enum.take(lines, n) == l,
      do: apply(Enum.drop(lines, n), rest, if(kind == :eq, do: [l | acc], else: acc)),
      else: :error
  end

  defp apply(_lines, _diff, _acc), do: :error
end
