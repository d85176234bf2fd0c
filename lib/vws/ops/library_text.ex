defmodule Vws.Ops.LibraryText do
  @moduledoc """
  The program library (`Vws.CEC.Library`) in words, for people: where the machine stands for a
  program, the compare as text lines (`mix vws.library list` and `compare`, iex), a diff of two
  versions, why a file is not an NC program. The dashboard (`Vws.Ops.Web.State`) and
  `Vws.Ops.LibraryCLI` print through it; the store itself prints nothing.
  """

  alias Vws.CEC.Library

  @doc """
  The words for a compare state, as iex, the dashboard and `mix vws.library` show them: `latest`
  is the number of the latest released version, `versions` (optional) the program's versions,
  so that a version from the machine is said to be one.

      iex> Vws.Ops.LibraryText.on_machine_text({:same, 3}, 3)
      "same"
      iex> Vws.Ops.LibraryText.on_machine_text({:same, 2}, 3)
      "same as v2 (not the latest)"
      iex> Vws.Ops.LibraryText.on_machine_text({:same, 4}, 3, [%{version: 4, source: "from the machine"}])
      "same as v4 (from the machine, not released)"
      iex> Vws.Ops.LibraryText.on_machine_text({:ambiguous, [1, 3]}, 3)
      "size and CRC of v1 and v3, which differ (read back to tell)"
  """
  @spec on_machine_text(Library.on_machine(), pos_integer | nil, [map]) :: String.t()
  def on_machine_text(state, latest, versions \\ [])
  def on_machine_text({:same, n}, latest, _) when n == latest, do: "same"

  def on_machine_text({:same, n}, _latest, versions) do
    case Enum.find(versions, &(&1.version == n and not Library.released?(&1))) do
      nil -> "same as v#{n} (not the latest)"
      v -> "same as v#{n} (#{Library.release_text(v)})"
    end
  end

  def on_machine_text({:ambiguous, ns}, _, _) do
    names =
      case Enum.map(ns, &"v#{&1}") do
        [one] -> one
        many -> Enum.join(Enum.drop(many, -1), ", ") <> " and " <> List.last(many)
      end

    "size and CRC of #{names}, which differ (read back to tell)"
  end

  def on_machine_text(:differs, _, _), do: "differs"
  def on_machine_text(:absent, _, _), do: "absent"
  def on_machine_text(:unknown, _, _), do: "unknown (directory not read yet)"
  def on_machine_text(:unreadable, _, _), do: "unknown (its directory line could not be read)"

  @doc """
  A compare (`Vws.CEC.Library.compare/1`, `Vws.Partitions.Monarch.compare/2`) as text lines: one per program —
  name, latest released version (else the newest, said to be from the machine), its source and
  time, size, CRC, and on the machine; then the versions from the machine newer than it — then
  the machine's files the library does not have.
  """
  @spec format_compare(map) :: [String.t()]
  def format_compare(%{read_at: read_at, programs: programs, machine_only: machine_only}) do
    head =
      case read_at do
        nil -> "machine directory: not read yet"
        at -> "machine directory read #{DateTime.to_iso8601(at)}"
      end

    rows =
      for p <- programs do
        v = p.latest || p.newest
        latest = p.latest && p.latest.version

        back =
          case Map.get(p, :read_back) do
            nil -> ""
            :same -> ", read back: same"
            :differs -> ", read back: differs"
            {:error, reason} -> ", read back failed: #{reason}"
          end

        newer =
          for u <- p.versions,
              not Library.released?(u),
              latest == nil or u.version > latest,
              do: u

        unreleased = Enum.map(newer, &"v#{&1.version}")

        "#{p.name}  v#{v.version} of #{length(p.versions)}#{if latest, do: "", else: " (#{not_released_text(newer)})"}" <>
          "  #{DateTime.to_iso8601(v.at)}  " <>
          "#{v.source}  #{v.size} bytes  CRC #{hex4(v.crc)}  on the machine: " <>
          on_machine_text(p.on_machine, latest, p.versions) <>
          back <>
          if(unreleased == [] or latest == nil,
            do: "",
            else: "  (newer, #{not_released_text(newer)}: #{Enum.join(unreleased, ", ")})"
          )
      end

    [head | rows] ++ Enum.map(machine_only, &"#{&1}  on the machine only")
  end

  @doc "Prints `format_compare/1` of `Vws.CEC.Library.compare/1` (or of a compare given), for iex."
  @spec print_compare(Library.lib() | map) :: :ok
  def print_compare(%{programs: _} = result), do: Enum.each(format_compare(result), &IO.puts/1)

  def print_compare(lib) do
    case Library.compare(lib) do
      {:ok, result} -> print_compare(result)
      {:error, reason} -> IO.puts("no library: #{inspect(reason)}")
    end
  end

  @doc """
  How versions that are not released are said: `"from the machine, not released"` (every one
  was sent from the machine), `"draft, not released"` (none was), else `"not released"`.

      iex> Vws.Ops.LibraryText.not_released_text([%{source: "from the machine"}])
      "from the machine, not released"
      iex> Vws.Ops.LibraryText.not_released_text([%{source: "cli"}])
      "draft, not released"
  """
  @spec not_released_text([map]) :: String.t()
  def not_released_text(versions) do
    case Enum.uniq(Enum.map(versions, &(&1.source == "from the machine"))) do
      [true] -> "from the machine, not released"
      [false] -> "draft, not released"
      _ -> "not released"
    end
  end

  @doc """
  The transfer history (`Vws.CEC.Library.history/2`) as text lines, one a transfer, as `mix
  vws.library history` prints them: when, program and version, direction, what it was, bytes
  and blocks, duration and rate, retries, result, who asked, what a compare found — then one
  line for each damaged part that was skipped.
  """
  @spec format_history(%{records: [map], damaged: [map]}) :: [String.t()]
  def format_history(%{records: records, damaged: damaged}) do
    rows =
      for r <- records do
        version = if r.version, do: "v#{r.version}", else: "(no library version)"

        "#{r.at}  #{r.program || "?"} #{version}  #{r.direction}  #{r.command}  " <>
          "#{r.bytes} bytes #{r.blocks} blocks  #{r.duration_ms} ms " <>
          "#{r.chars_per_s} B/s  retries #{r.retries}  #{r.result}  by #{r.requester}" <>
          if(r.note, do: "  — #{r.note}", else: "")
      end

    rows ++
      for d <- damaged do
        "DAMAGED: #{d.file} from byte #{d.offset} (#{d.why}): a record there was skipped"
      end
  end

  @doc "Prints the transfer history of `lib` (iex): options as `Vws.CEC.Library.history/2`."
  @spec print_history(Library.lib(), keyword) :: :ok
  def print_history(lib, opts \\ []) do
    case Library.history(lib, opts) do
      {:ok, h} -> Enum.each(format_history(h), &IO.puts/1)
      {:error, reason} -> IO.puts("no history: #{inspect(reason)}")
    end
  end

  defp hex4(crc), do: String.pad_leading(Integer.to_string(crc, 16), 4, "0")

  @doc """
  A diff as text: `-` before a line only in the first version, `+` only in the second, two blanks
  before a line in both; runs of more than six common lines are cut to their first and last
  three. An empty diff (`[]` or all common) prints as nothing.
  """
  @spec format_diff([{:eq | :del | :ins, [binary]}]) :: [String.t()]
  def format_diff(diff) do
    if Enum.all?(diff, &(elem(&1, 0) == :eq)) do
      []
    else
      Enum.flat_map(diff, fn
        {:del, lines} ->
          Enum.map(lines, &("- " <> &1))

        {:ins, lines} ->
          Enum.map(lines, &("+ " <> &1))

        {:eq, lines} when length(lines) > 6 ->
          Enum.map(Enum.take(lines, 3), &("  " <> &1)) ++
            ["  … #{length(lines) - 6} lines the same …"] ++
            Enum.map(Enum.take(lines, -3), &("  " <> &1))

        {:eq, lines} ->
          Enum.map(lines, &("  " <> &1))
      end)
    end
  end

  @doc """
  Why `Vws.CEC.Library.check_program/1` refused a file, in words (for `mix vws.library import`).

      iex> Vws.Ops.LibraryText.program_refusal(:no_start)
      "not an NC program: its first line is not %"
  """
  @spec program_refusal(term) :: String.t()
  def program_refusal(why), do: "not an NC program: " <> refusal(why)

  defp refusal({:too_large, size}),
    do: "#{size} bytes, more than the #{Library.max_bytes()} bytes the library keeps"

  defp refusal({:binary, offset}), do: "a binary file (not text at byte #{offset})"

  defp refusal({:control, byte, line}),
    do: "control character 0x#{Base.encode16(<<byte>>)} on line #{line}"

  defp refusal(:no_start), do: "its first line is not %"
  defp refusal(:no_end), do: "its last line is not % (ending with a line feed)"

  defp refusal(:no_program_number),
    do: "no program number (an O word, or : in EIA) on the line after the opening %"

  defp refusal(:bad_program_number), do: "its program number has more than six digits"
end
