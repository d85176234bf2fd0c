defmodule Vws.Codecs.NCModalTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.NCModal

  doctest NCModal

  @program [
    "%",
    "O1234 (BRACKET)",
    "G20 G17 G90 G54",
    "T4 M6",
    "S1200 M3",
    "M8",
    "G0 X0 Y0",
    "G1 Z-0.1 F20.",
    "X1.5 ; a comment",
    "G81 R0.1 Z-0.5 F10",
    "X2",
    "X3",
    "G80",
    "T7",
    "G2 X4 Y1 I0.5 J0 F15",
    "M9",
    "M5",
    "M30",
    "%"
  ]

  test "restart at a line: the head, a comment, the preamble of the state before it, then the line on" do
    assert {:ok, preamble, lines} = NCModal.restart(@program, 9)
    assert preamble == ["G20 G17 G90 G54", "T4 M6", "S1200 M3", "M8", "G1 F20."]

    assert lines ==
             ["%", "O1234 (BRACKET)", "(RESTART AT LINE 9)" | preamble] ++
               Enum.drop(@program, 8)
  end

  test "after a canned cycle ended with G80: the cycle is not restored, the tool selected is" do
    assert {:ok, preamble, _} = NCModal.restart(@program, 15)
    assert preamble == ["G20 G17 G90 G54", "T4 M6", "T7", "S1200 M3", "M8", "G1 F10"]
  end

  test "inside a canned cycle (G81 … G80): refused in words" do
    for n <- [11, 12, 13] do
      assert NCModal.restart(@program, n) ==
               {:error, "RESTART LINE #{n} INSIDE A CANNED CYCLE G81 (NO G80 BEFORE IT)"}
    end

    # the cycle's own first line starts it: a restart there is allowed
    assert {:ok, _, _} = NCModal.restart(@program, 10)
  end

  test "beyond the end, or at the closing %: refused in words" do
    assert NCModal.restart(@program, 19) ==
             {:error, "RESTART LINE 19 BEYOND THE END (LAST BLOCK 18)"}

    assert NCModal.restart(@program, 500) ==
             {:error, "RESTART LINE 500 BEYOND THE END (LAST BLOCK 18)"}

    assert {:ok, _, _} = NCModal.restart(@program, 18)
  end

  test "at or before the program number's line: the whole program" do
    assert NCModal.restart(@program, 1) == {:ok, [], @program}
    assert NCModal.restart(@program, 2) == {:ok, [], @program}
  end

  test "comments, block delete and other words leave the state alone; 01 and 1 are one code" do
    s = NCModal.state(["/G91 (G90 M8) X1", "N10 G01 M03 S5 (M4", "Y2 ; G20 M9 F9"])
    assert %{distance: "G91", motion: "G01", spindle: "M03", speed: "S5", units: nil} = s
    assert s.flood == false and s.feed == nil
  end

  ## Properties

  defp word_gen do
    :proper_types.oneof([
      :proper_types.elements(
        ~w(G0 G1 G01 G2 G3 G17 G18 G19 G20 G21 G70 G71 G90 G91 G54 G55 G59 G80 G81 G83 M3 M4 M5 M6 M7 M8 M9 M30)
      ),
      :proper_types.elements([
        "X1",
        "Y-2.5",
        "Z0.1",
        "I1",
        "J-1",
        "R0.1",
        "N10",
        "F100",
        "F25.",
        "S800",
        "S1500",
        "T1",
        "T12",
        "(NOTE)",
        ";C"
      ]),
      :proper_types.elements(["F", "S", "T"])
    ])
  end

  defp program_gen do
    :proper_types.list(:proper_types.non_empty(:proper_types.list(word_gen())))
  end

  defp text(lines), do: Enum.map(lines, &Enum.join(&1, " "))

  test "property: the state after the restarted program's head and preamble is the state at line N; running on from there ends as the whole program does" do
    property =
      :proper.forall({program_gen(), :proper_types.pos_integer()}, fn {body, k} ->
        lines = ["%", "O42"] ++ text(body) ++ ["%"]
        n = rem(k, length(lines) + 3) + 1

        case NCModal.restart(lines, n) do
          {:ok, [], ^lines} ->
            n <= 2

          {:ok, preamble, restarted} ->
            before = NCModal.state(Enum.take(lines, n - 1))
            head = Enum.take(restarted, 3 + length(preamble))

            NCModal.state(head) == before and
              NCModal.state(restarted) == NCModal.state(lines) and
              Enum.drop(restarted, 3 + length(preamble)) == Enum.drop(lines, n - 1) and
              before.cycle == nil

          {:error, "RESTART LINE " <> _ = why} ->
            if why =~ "CANNED CYCLE",
              do: NCModal.state(Enum.take(lines, n - 1)).cycle != nil,
              else: n >= length(lines)
        end
      end)

    assert_property(property, 500)
  end

  test "property: random text never crashes the modal state nor the restart" do
    property =
      :proper.forall(
        {:proper_types.list(:proper_types.binary()), :proper_types.pos_integer()},
        fn {lines, n} ->
          (is_map(NCModal.state(lines)) and
             match?({tag, _, _} when tag == :ok, NCModal.restart(lines, n))) or
            match?({:error, _}, NCModal.restart(lines, n))
        end
      )

    assert_property(property, 300)
  end
end
