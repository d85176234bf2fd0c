defmodule Vws.CEC.Library.Workflow do
  @moduledoc """
  The library workflow's state of each version (issue 27): released or draft, its comment, and
  the tombstone of a deleted version — kept beside the versions, which never change once stored.

      <library>/.state/004711.PRO~000003     the state of version 3 of 004711.PRO

  A version without a state file is released unless it came from the machine (its source
  `"from the machine"`: a draft), as before the workflow. A state file holds one frame of the
  journal's format (`Vws.CEC.Journal.Log`: CRC-32s over header and record) and its end mark,
  written whole (a temporary file, synced, renamed, the directory synced):

      %{state: :released | :draft | :deleted, comment: String.t() | nil,
        changes: [%{at: ISO 8601, by: String.t(), what: String.t()}],   # oldest first
        deleted: nil | %{size, crc, digest, source, at}}                 # what the version was

  A state file that cannot be read (damaged) makes its version a **draft** — never sent to a
  machine by `DOWNLOAD_GE(nnnnnn.PRO)` — and is logged; `state/3` says `{:error, :damaged}`.
  Pure file work on a library directory: `Vws.CEC.Library` is the interface.
  """

  require Logger
  alias Vws.CEC.Journal.Log
  alias Vws.CEC.Library.Files

  @dir ".state"

  @doc "The state file of version `n` of `name` in library directory `dir`."
  @spec path(Path.t(), String.t(), pos_integer) :: Path.t()
  def path(dir, name, n), do: Path.join([dir, @dir, "#{name}~#{Files.pad(n, 6)}"])

  @doc "The state of a version: `{:ok, state}`, `:none` (no state file) or `{:error, :damaged}`."
  @spec state(Path.t(), String.t(), pos_integer) :: {:ok, map} | :none | {:error, term}
  def state(dir, name, n) do
    case File.read(path(dir, name, n)) do
      {:ok, bin} -> decode(bin, name, n)
      {:error, :enoent} -> :none
      {:error, reason} -> {:error, reason}
    end
  end

  defp decode(bin, name, n) do
    with [{:record, 0, payload}] <- Log.parse(bin),
         %{state: s, comment: c, changes: ch} = state when s in [:released, :draft, :deleted] <-
           safe_term(payload),
         true <- (is_nil(c) or is_binary(c)) and is_list(ch) do
      {:ok, Map.put_new(state, :deleted, nil)}
    else
      _ ->
        Logger.error(
          "program library: the state of #{name} v#{n} is damaged: taken as a draft " <>
            "(set it again: release, unrelease or comment)"
        )

        {:error, :damaged}
    end
  end

  defp safe_term(payload) do
    :erlang.binary_to_term(payload, [:safe])
  rescue
    ArgumentError -> nil
  end

  @doc """
  Changes the state of version `n` with `fun` (the state before, or the default for `v` when
  it has none), noting `what` by `by`; writes it whole. `{:ok, state}` or `{:error, reason}`.
  """
  @spec change(Path.t(), map, String.t(), String.t(), (map -> map)) :: {:ok, map} | {:error, term}
  def change(dir, v, by, what, fun) do
    before =
      case state(dir, v.name, v.version) do
        {:ok, s} -> s
        _ -> default(v)
      end

    at = DateTime.utc_now() |> DateTime.truncate(:millisecond) |> DateTime.to_iso8601()
    new = fun.(before) |> Map.update!(:changes, &(&1 ++ [%{at: at, by: by, what: what}]))
    file = path(dir, v.name, v.version)

    with :ok <- File.mkdir_p(Path.dirname(file)),
         :ok <-
           Files.write_whole(
             Files.tmp_path(Path.dirname(file), Path.basename(file)),
             file,
             [Log.record(new), Log.end_mark()]
           ),
         :ok <- Files.sync_dir(Path.dirname(file)),
         do: {:ok, new}
  end

  @doc "The state a version has without a state file."
  @spec default(map) :: map
  def default(v) do
    %{
      state: if(v.source == "from the machine", do: :draft, else: :released),
      comment: nil,
      changes: [],
      deleted: nil
    }
  end

  @doc """
  `versions` (of library directory `dir`, as `Vws.CEC.Library.Files.parse_files/1` gives them)
  with their workflow state: `state` (`:released` or `:draft`), `released`, `comment`; deleted
  versions (a tombstone) are left out.
  """
  @spec apply_states([map], Path.t()) :: [map]
  def apply_states(versions, dir) do
    # one listing of the state directory: most versions have no state file
    present =
      case Files.ls(Path.join(dir, @dir)) do
        {:ok, names} -> MapSet.new(names)
        _ -> MapSet.new()
      end

    Enum.flat_map(versions, fn v ->
      s =
        if MapSet.member?(present, "#{v.name}~#{Files.pad(v.version, 6)}") do
          case state(dir, v.name, v.version) do
            {:ok, s} -> s
            {:error, _} -> %{default(v) | state: :draft}
            :none -> default(v)
          end
        else
          default(v)
        end

      if s.state == :deleted,
        do: [],
        else: [
          Map.merge(v, %{state: s.state, released: s.state == :released, comment: s.comment})
        ]
    end)
  end

  @doc """
  The tombstones of library directory `dir` (of `name` only when given): `[%{name, version,
  comment, changes, deleted}]`, by name and version.
  """
  @spec tombstones(Path.t(), String.t() | nil) :: [map]
  def tombstones(dir, name \\ nil) do
    case Files.ls(Path.join(dir, @dir)) do
      {:ok, files} ->
        for <<n::binary-10, "~", v::binary-6>> <- files,
            name == nil or n == name,
            {version, ""} <- [Integer.parse(v)],
            {:ok, %{state: :deleted} = s} <- [state(dir, n, version)] do
          Map.merge(s, %{name: n, version: version})
        end
        |> Enum.sort_by(&{&1.name, &1.version})

      _ ->
        []
    end
  end
end
