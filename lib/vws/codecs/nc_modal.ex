defmodule Vws.Codecs.NCModal do
  @moduledoc """
  The modal state of an NC program (word address, RS-274 style as the GE-2000 reads it) and the
  restart of a program at a chosen line with that state restored (ours, issue 27 item 2;
  docs/dnc-drip-feed.md "Restart at a block"). Pure: lines in, lines out.

  What is modal, and kept (the word as the program wrote it, so the preamble says it the same way):

  | group | words |
  |-------|-------|
  | motion | `G0` `G1` `G2` `G3` |
  | plane | `G17` `G18` `G19` |
  | units | `G20` `G21` (or `G70` `G71`) |
  | distance | `G90` `G91` |
  | work offset | `G54` … `G59` |
  | feed | `F` |
  | spindle speed | `S`; direction `M3` `M4` `M5` |
  | tool | `T` (selected), and the tool in the spindle after `M6` |
  | coolant | `M7` (mist) and `M8` (flood), `M9` both off |
  | canned cycle | `G81` … `G89` active until `G80` or a motion `G0`–`G3` |

  A line's comments — `(…)` and from `;` to its end — and a leading `/` (block delete) are not
  words; `N` (sequence numbers), coordinates and every other word leave the state alone.

      iex> s = Vws.Codecs.NCModal.state(["%", "O1", "G21 G90 G54", "T3 M6", "S900 M3", "G1 X1 F80"])
      iex> Vws.Codecs.NCModal.preamble(s)
      ["G21 G90 G54", "T3 M6", "S900 M3", "G1 F80"]
  """

  @type t :: %{
          motion: String.t() | nil,
          plane: String.t() | nil,
          units: String.t() | nil,
          distance: String.t() | nil,
          offset: String.t() | nil,
          feed: String.t() | nil,
          speed: String.t() | nil,
          spindle: String.t() | nil,
          tool: String.t() | nil,
          loaded: String.t() | nil,
          mist: boolean,
          flood: boolean,
          cycle: String.t() | nil
        }

  @empty %{
    motion: nil,
    plane: nil,
    units: nil,
    distance: nil,
    offset: nil,
    feed: nil,
    speed: nil,
    spindle: nil,
    tool: nil,
    loaded: nil,
    mist: false,
    flood: false,
    cycle: nil
  }

  @doc "The state before any line."
  @spec initial() :: t
  def initial, do: @empty

  @doc "The modal state after `lines` (from `initial/0`, or from `state`)."
  @spec state([String.t()], t) :: t
  def state(lines, state \\ @empty), do: Enum.reduce(lines, state, &line/2)

  @doc """
  The lines that set `state` from the initial one: units, plane, distance and work offset; the
  tool in the spindle (`T… M6`) and one selected after it; spindle speed and direction; coolant;
  motion mode and feed. A canned cycle is never restored (`restart/2` refuses to start inside one).
  """
  @spec preamble(t) :: [String.t()]
  def preamble(s) do
    [
      words([s.units, s.plane, s.distance, s.offset]),
      if(s.loaded, do: words([s.loaded, "M6"])),
      if(s.tool && s.tool != s.loaded, do: s.tool),
      words([s.speed, s.spindle]),
      words([if(s.mist, do: "M7"), if(s.flood, do: "M8")]),
      words([s.motion, s.feed])
    ]
    |> Enum.reject(&(&1 in [nil, ""]))
  end

  @doc """
  The program `lines` restarted at line `n` (1 = the first line, as the library counts them):
  `{:ok, preamble, lines}` — the program's head (its leading `%` and its `O`/`:` number line),
  then a comment naming the restart and the preamble that restores the modal state of the lines
  before `n`, then line `n` to the end — or `{:error, words}` (upper-case words and numbers):
  `n` past the program's last line before its closing `%`, or inside a canned cycle.
  A restart at or before the program number's line is the whole program (`preamble` `[]`).
  """
  @spec restart([String.t()], pos_integer) ::
          {:ok, [String.t()], [String.t()]} | {:error, String.t()}
  def restart(lines, n) when is_integer(n) and n >= 1 do
    head_count = head_count(lines)
    last = last_block(lines)

    cond do
      n <= head_count ->
        {:ok, [], lines}

      n > last ->
        {:error, "RESTART LINE #{n} BEYOND THE END (LAST BLOCK #{last})"}

      true ->
        before = Enum.slice(lines, 0, n - 1)
        s = state(before)

        if s.cycle do
          {:error, "RESTART LINE #{n} INSIDE A CANNED CYCLE #{s.cycle} (NO G80 BEFORE IT)"}
        else
          preamble = preamble(s)
          head = Enum.take(lines, head_count)
          comment = "(RESTART AT LINE #{n})"
          {:ok, preamble, head ++ [comment | preamble] ++ Enum.drop(lines, n - 1)}
        end
    end
  end

  # the leading "%" (the tape's rewind stop) and the program number's line
  defp head_count(lines) do
    case lines do
      ["%", number | _] -> if number?(number), do: 2, else: 1
      ["%" | _] -> 1
      [number | _] -> if number?(number), do: 1, else: 0
      [] -> 0
    end
  end

  defp number?(line), do: String.trim_leading(line) =~ ~r/^[O:]\d/i

  # the last line that can be restarted at: the one before the closing "%"
  defp last_block(lines) do
    count = length(lines)
    if count > 1 and String.trim(List.last(lines)) == "%", do: count - 1, else: count
  end

  ## One line

  defp line(text, s) do
    text
    |> strip()
    |> parse_words()
    |> Enum.reduce(s, &word/2)
  end

  defp strip(text) do
    text = text |> String.split(";", parts: 2) |> hd()
    text = Regex.replace(~r/\([^)]*\)?/, text, " ")
    text |> String.trim_leading() |> String.trim_leading("/")
  end

  defp parse_words(text) do
    ~r/([A-Za-z])\s*([-+]?[0-9]*\.?[0-9]*)/
    |> Regex.scan(text, capture: :all_but_first)
    |> Enum.map(fn [letter, value] -> {String.upcase(letter), value} end)
  end

  defp word({"G", value} = w, s) do
    case code(value) do
      n when n in 0..3 -> %{s | motion: text(w), cycle: nil}
      n when n in 17..19 -> %{s | plane: text(w)}
      n when n in [20, 21, 70, 71] -> %{s | units: text(w)}
      n when n in [90, 91] -> %{s | distance: text(w)}
      n when n in 54..59 -> %{s | offset: text(w)}
      80 -> %{s | cycle: nil}
      n when n in 81..89 -> %{s | cycle: text(w)}
      _ -> s
    end
  end

  defp word({"M", value} = w, s) do
    case code(value) do
      n when n in 3..5 -> %{s | spindle: text(w)}
      6 -> %{s | loaded: s.tool}
      7 -> %{s | mist: true}
      8 -> %{s | flood: true}
      9 -> %{s | mist: false, flood: false}
      _ -> s
    end
  end

  defp word({"F", _} = w, s), do: %{s | feed: text(w)}
  defp word({"S", _} = w, s), do: %{s | speed: text(w)}
  defp word({"T", _} = w, s), do: %{s | tool: text(w)}
  defp word(_w, s), do: s

  # a G or M code's number: 1, 01 and 1.0 are the same code; G54.1 and the like are none here
  defp code(value) do
    case Float.parse(value) do
      {f, ""} when f == trunc(f) -> trunc(f)
      _ -> nil
    end
  end

  defp text({letter, value}), do: letter <> value

  defp words(list), do: list |> Enum.reject(&is_nil/1) |> Enum.join(" ")
end
