defmodule Vws.CEC.Library.Files do
  @moduledoc """
  The program library on disk (`Vws.CEC.Library`): a version's file name, which carries what a
  listing shows (`<program>~<version>~<stored at, UTC>~<source>~<size>~<CRC>~<SHA-256>`), read
  back from a directory listing; the version numbers taken as symbolic links under `.v/`; and
  files written whole (a synced temporary file, renamed; the directory synced).

  The size is written with at least six digits (`001234`, as every version was named while the
  library kept only what the GE-2000's directory can say, 999,999 bytes) and as many as it takes
  above that (`1500000`, up to `Vws.CEC.Library.max_bytes/0`): a listing reads any number of
  digits, so libraries written in either form read alike.
  """

  alias Vws.CEC.Library.Version

  @numbers ".v"
  @tmp_prefix ".tmp-"

  @doc "The directory of the number links of library directory `dir`."
  @spec numbers_dir(Path.t()) :: Path.t()
  def numbers_dir(dir), do: Path.join(dir, @numbers)

  @doc """
  Takes version number `n` of `v`, else the next free one, by creating the link
  `.v/<name>~<version>` → the version's file name: the link's creation fails when the number is
  taken, in whatever process took it. `{:ok, v}` with its `version` and `file`.
  """
  @spec take_number(Path.t(), map, pos_integer) :: {:ok, map} | {:error, term}
  def take_number(dir, v, n) when n < 1_000_000 do
    v = %{v | version: n, file: file_name(%{v | version: n})}

    case File.ln_s(Path.join("..", v.file), number_link(dir, v.name, n)) do
      :ok -> {:ok, v}
      {:error, :eexist} -> take_number(dir, v, n + 1)
      error -> error
    end
  end

  def take_number(_dir, _v, _n), do: {:error, :too_many_versions}

  @doc "`.v/<name>~<version>`: kept apart, so that a listing reads only the versions' own names."
  @spec number_link(Path.t(), String.t(), pos_integer) :: Path.t()
  def number_link(dir, name, n), do: Path.join([dir, @numbers, "#{name}~#{pad(n, 6)}"])

  @doc """
  Where to start looking for a free number: after the last number taken (a link that exists,
  whether its version was finished or not), found by halving.
  """
  @spec first_free(Path.t(), String.t()) :: pos_integer
  def first_free(dir, name) do
    taken? = fn n ->
      match?({:ok, _}, :file.read_link_info(number_link(dir, name, n)))
    end

    hi = Stream.iterate(1, &(&1 * 2)) |> Enum.find(&(not taken?.(&1) or &1 >= 1_000_000))
    first_free(taken?, div(hi, 2), hi)
  end

  defp first_free(_taken?, lo, hi) when hi - lo <= 1, do: max(hi, 1)

  defp first_free(taken?, lo, hi) do
    mid = div(lo + hi, 2)
    if taken?.(mid), do: first_free(taken?, mid, hi), else: first_free(taken?, lo, mid)
  end

  @doc "The names in `dir` as binaries (`{:ok, []}` when it does not exist)."
  @spec ls(Path.t()) :: {:ok, [String.t()]} | {:error, term}
  def ls(dir) do
    case :prim_file.list_dir(dir) do
      # the library's own names are ASCII: list_to_binary/1 is the quick way; any other name
      # (not the library's) is converted properly, and then skipped
      {:ok, names} -> {:ok, Enum.map(names, &name_to_binary/1)}
      {:error, :enoent} -> {:ok, []}
      error -> error
    end
  end

  defp name_to_binary(name) do
    :erlang.list_to_binary(name)
  rescue
    ArgumentError -> IO.chardata_to_string(name)
  end

  @doc """
  The versions named among `files`. Only whole version names count; the number links, temporary
  files, MACHINE.DIR and anything foreign are skipped. A name without a digest (stored before
  versions had one) gets `digest: nil`: `with_digests/2` reads its bytes.
  """
  # (binary matches, no regular expressions: a listing parses every name of the directory)
  @spec parse_files([String.t()]) :: [Version.t()]
  def parse_files(files) do
    for <<name::binary-10, "~", n::binary-6, "~", rest::binary>> = file <- files,
        stored_name?(name),
        [at, source, size, crc | digest] <- [:binary.split(rest, "~", [:global])],
        digest <- parse_digest(digest),
        v when v > 0 <- [int(n, 10)],
        size when size >= 0 <- [int(size, 10)],
        crc when crc >= 0 <- [int(crc, 16)],
        {:ok, at} <- [parse_at(at)] do
      Version.with_origin(%{
        name: name,
        version: v,
        at: at,
        source:
          if(:binary.match(source, "+") == :nomatch,
            do: source,
            else: String.replace(source, "+", " ")
          ),
        size: size,
        crc: crc,
        digest: digest,
        file: file
      })
    end
  end

  # [] (a version stored before digests) → nil; 64 lower-case hexadecimal digits; else none
  defp parse_digest([]), do: [nil]
  defp parse_digest([<<_::binary-64>> = d]), do: if(hex?(d), do: [d], else: [])
  defp parse_digest(_), do: []

  defp hex?(<<>>), do: true
  defp hex?(<<c, rest::binary>>) when c in ?0..?9 or c in ?a..?f, do: hex?(rest)
  defp hex?(_), do: false

  @doc """
  A version stored before versions had a digest gets it, computed from its bytes when they are
  whole (size and CRC as stored); a file that is not keeps `digest: nil` — it is the same as no
  other version, and reads as damaged.
  """
  @spec with_digests([Version.t()], Path.t()) :: [Version.t()]
  def with_digests(versions, dir) do
    Enum.map(versions, fn
      %{digest: nil} = v ->
        case File.read(Path.join(dir, v.file)) do
          {:ok, bytes} ->
            if byte_size(bytes) == v.size and Vws.Codecs.CRC16.compute(bytes) == v.crc,
              do: %{v | digest: Version.digest(bytes)},
              else: v

          _ ->
            v
        end

      v ->
        v
    end)
  end

  @doc "A version's file name, from its fields."
  @spec file_name(map) :: String.t()
  def file_name(v) do
    Enum.join(
      [
        v.name,
        pad(v.version, 6),
        format_at(v.at),
        String.replace(v.source, " ", "+"),
        pad(v.size, 6),
        String.pad_leading(Integer.to_string(v.crc, 16), 4, "0"),
        v.digest
      ],
      "~"
    )
  end

  # 20261125T090000.123Z
  defp format_at(at) do
    {ms, _} = at.microsecond

    :io_lib.format("~4..0B~2..0B~2..0BT~2..0B~2..0B~2..0B.~3..0BZ", [
      at.year,
      at.month,
      at.day,
      at.hour,
      at.minute,
      at.second,
      div(ms, 1000)
    ])
    |> IO.iodata_to_binary()
  end

  # a name as store/4 writes it: six digits, .PRO or .GSU
  defp stored_name?(<<digits::binary-6, ".", ext::binary-3>>) when ext in ["PRO", "GSU"],
    do: digits?(digits)

  defp stored_name?(_), do: false

  defp digits?(<<>>), do: true
  defp digits?(<<c, rest::binary>>) when c in ?0..?9, do: digits?(rest)
  defp digits?(_), do: false

  # digits only (no sign, no blanks) as an integer, else -1
  defp int(text, base) do
    if base == 16 or digits?(text), do: :erlang.binary_to_integer(text, base), else: -1
  rescue
    ArgumentError -> -1
  end

  defp parse_at(
         <<y::binary-4, mo::binary-2, d::binary-2, "T", h::binary-2, mi::binary-2, s::binary-2,
           ".", ms::binary-3, "Z">>
       ) do
    [y, mo, d, h, mi, s, ms] = for part <- [y, mo, d, h, mi, s, ms], do: int(part, 10)

    with true <- Enum.min([y, mo, d, h, mi, s, ms]) >= 0,
         true <- :calendar.valid_date(y, mo, d) and h < 24 and mi < 60 and s < 60 do
      {:ok,
       %DateTime{
         year: y,
         month: mo,
         day: d,
         hour: h,
         minute: mi,
         second: s,
         microsecond: {ms * 1000, 3},
         time_zone: "Etc/UTC",
         zone_abbr: "UTC",
         utc_offset: 0,
         std_offset: 0
       }}
    else
      _ -> :error
    end
  end

  defp parse_at(_), do: :error

  @doc false
  def pad(n, width), do: String.pad_leading(Integer.to_string(n), width, "0")

  @doc "Writes `bytes` to the new file `path` and syncs it; the file is removed on failure."
  @spec write_synced(Path.t(), iodata) :: :ok | {:error, term}
  def write_synced(path, bytes) do
    with {:ok, fd} <- :file.open(path, [:write, :exclusive, :raw, :binary]) do
      result = with :ok <- :file.write(fd, bytes), do: :file.sync(fd)
      :file.close(fd)
      if result != :ok, do: File.rm(path)
      result
    end
  end

  @doc "A new temporary file's path in `dir`, for `name` (hidden: a listing skips it)."
  @spec tmp_path(Path.t(), String.t()) :: Path.t()
  def tmp_path(dir, name),
    do:
      Path.join(
        dir,
        "#{@tmp_prefix}#{name}-#{:os.getpid()}-#{System.unique_integer([:positive])}"
      )

  @doc "True for the name of a temporary file (`tmp_path/2`)."
  @spec tmp?(String.t()) :: boolean
  def tmp?(file), do: String.starts_with?(file, @tmp_prefix)

  @doc """
  Writes `bytes` whole to `path`: to the new file `tmp` first, synced, then renamed over `path`
  — a crash leaves the old `path` or the new one, never a part. `tmp` is removed on failure.
  """
  @spec write_whole(Path.t(), Path.t(), iodata) :: :ok | {:error, term}
  def write_whole(tmp, path, bytes) do
    with :ok <- write_synced(tmp, bytes), do: rename_or_remove(tmp, path)
  end

  @doc "Renames `tmp` to `path`; removes `tmp` when the rename fails."
  @spec rename_or_remove(Path.t(), Path.t()) :: :ok | {:error, term}
  def rename_or_remove(tmp, path) do
    with {:error, _} = error <- :file.rename(tmp, path) do
      File.rm(tmp)
      error
    end
  end

  @doc "Syncs directory `dir` (a rename in it is on disk)."
  @spec sync_dir(Path.t()) :: :ok | {:error, term}
  def sync_dir(dir) do
    case :file.open(dir, [:read, :raw, :directory]) do
      {:ok, fd} ->
        result = :file.sync(fd)
        :file.close(fd)
        result

      error ->
        error
    end
  end
end
