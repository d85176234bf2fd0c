defmodule Vws.CEC.Library.DiffTest do
  # Line diffs (issue 27): the edit script applied to the first text's lines gives the
  # second's, and the printed diff, read back, gives it too.
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.CEC.Library.Diff

  doctest Diff

  # NC-like lines from a small alphabet, so that random lists share lines
  defp lines_gen do
    :proper_types.list(
      :proper_types.elements(["%", "O1", "N10 G00 X0", "N20 G01 X1 F300", "M30", "", "(NOTE)"])
    )
  end

  defp text(lines), do: IO.iodata_to_binary(Enum.map(lines, &[&1, ?\n]))

  test "property: the diff of A and B applied to A gives B; its counts are what it removes and adds" do
    property =
      :proper.forall({lines_gen(), lines_gen()}, fn {a, b} ->
        d = Diff.lines(text(a), text(b))
        s = Diff.summary(d)

        Diff.apply(a, d) == {:ok, b} and
          s.removed == length(a) - Enum.sum(for {:eq, l} <- d, do: length(l)) and
          s.added == length(b) - Enum.sum(for {:eq, l} <- d, do: length(l)) and
          s.first_line == nil == (a == b)
      end)

    assert_property(property, 500)
  end

  test "property: the printed diff (- and + lines, all common lines kept) rebuilds B from A" do
    property =
      :proper.forall({lines_gen(), lines_gen()}, fn {a, b} ->
        printed =
          Enum.flat_map(Diff.lines(text(a), text(b)), fn
            {:eq, l} -> Enum.map(l, &("  " <> &1))
            {:del, l} -> Enum.map(l, &("- " <> &1))
            {:ins, l} -> Enum.map(l, &("+ " <> &1))
          end)

        rebuilt =
          for line <- printed, not String.starts_with?(line, "- "), do: String.slice(line, 2..-1)

        kept_and_removed =
          for line <- printed, not String.starts_with?(line, "+ "), do: String.slice(line, 2..-1)

        rebuilt == b and kept_and_removed == a
      end)

    assert_property(property, 500)
  end

  test "a script made for another text is refused" do
    d = Diff.lines("%\nA\n%\n", "%\nB\n%\n")
    assert Diff.apply(["%", "C", "%"], d) == :error
    assert Diff.summary(Diff.lines("%\n", "%\n")) == %{removed: 0, added: 0, first_line: nil}
  end
end
