defmodule Vws.CEC.Library.History do
  @moduledoc """
  The transfer history of a program library (issue 27): one record per NC program transfer
  MONARCH made — program, version, direction, bytes, blocks, duration, rate, result, retries,
  who asked — durable, bounded and checked record by record. `Vws.CEC.Library.record_transfer/2`
  and `Vws.CEC.Library.history/2` are its interface; `docs/program-library.md` "Transfer
  history" the decisions.

  ## On disk

      <library>/history/transfers.log      the records being written
      <library>/history/transfers.1.log    the file before it (rotated), … up to transfers.<keep>.log

  Each file is a sequence of frames of the journal's format (`Vws.CEC.Journal.Log`: `"VJ"`, kind,
  length, CRC-32 of the header, the record as `:erlang.term_to_binary/1`, CRC-32 of the record),
  each append one write of the record *and an end mark* over the end mark before it, then
  `fsync` — so a file written whole ends with its one end mark (a file cut short anywhere, even
  between two records, does not), and a record cut short by a crash, or damaged later, fails its CRC-32s:
  it is skipped and told (`read/1`'s `damaged`, and a log line with the file and byte offset),
  never read as another record. A record whose frame holds but whose fields are not a transfer
  record (a newer version's, or a CRC-32 collision) is skipped and told the same way.

  **Bounded** (decision): when the current file would grow past `max_bytes` (default 1 MiB,
  about 2,700 records) it is renamed `transfers.1.log` (the older ones move up one, the one past
  `keep`, default 4, is removed) and a new one is begun: at most `(keep + 1) × max_bytes` on disk,
  the newest records always kept. A file whose last bytes are not an end mark (the workstation
  was killed in the middle of an append) is rotated the same way before the next append, so
  the torn record stays where it is, told as damage, and never hides a later record.

  Appends from the processes of one node are serialised (`:global.trans/3` on the directory);
  only the workstation that runs MONARCH writes its library's history.
  """

  require Logger
  alias Vws.CEC.Journal.Log

  @current "transfers.log"
  @max_bytes 1_048_576
  @keep 4

  @typedoc "One transfer, as recorded."
  @type record :: %{
          id: pos_integer,
          at: String.t(),
          program: String.t() | nil,
          version: pos_integer | nil,
          digest: String.t() | nil,
          command: String.t(),
          operation: String.t(),
          direction: String.t(),
          bytes: non_neg_integer,
          blocks: non_neg_integer,
          duration_ms: non_neg_integer,
          chars_per_s: non_neg_integer,
          result: String.t(),
          retries: non_neg_integer,
          requester: String.t(),
          note: String.t() | nil
        }

  @fields %{
    id: &is_integer/1,
    at: &is_binary/1,
    program: &__MODULE__.binary_or_nil?/1,
    version: &__MODULE__.integer_or_nil?/1,
    digest: &__MODULE__.binary_or_nil?/1,
    command: &is_binary/1,
    operation: &is_binary/1,
    direction: &is_binary/1,
    bytes: &is_integer/1,
    blocks: &is_integer/1,
    duration_ms: &is_integer/1,
    chars_per_s: &is_integer/1,
    result: &is_binary/1,
    retries: &is_integer/1,
    requester: &is_binary/1,
    note: &__MODULE__.binary_or_nil?/1
  }

  @field_count map_size(@fields)

  @doc "The default bound: `max_bytes` per file and `keep` rotated files."
  @spec defaults() :: keyword
  def defaults, do: [max_bytes: @max_bytes, keep: @keep]

  @doc "The fields of a record (every one is present in every record)."
  @spec fields() :: [atom]
  def fields, do: Map.keys(@fields)

  @doc """
  A record from `fields` (those missing get their empty value: nil, 0, `""`), with a new `id`
  and `at` (now, UTC, ms) unless given.
  """
  @spec new(map | keyword) :: record
  def new(fields) do
    fields = Map.new(fields)

    defaults = %{
      id: System.os_time(:microsecond) * 1000 + rem(System.unique_integer([:positive]), 1000),
      at: DateTime.utc_now() |> DateTime.truncate(:millisecond) |> DateTime.to_iso8601(),
      command: "",
      operation: "",
      direction: "",
      bytes: 0,
      blocks: 0,
      duration_ms: 0,
      chars_per_s: 0,
      result: "",
      retries: 0,
      requester: ""
    }

    for {k, _} <- @fields, into: %{}, do: {k, Map.get(fields, k, Map.get(defaults, k))}
  end

  @doc """
  Appends `record` to the history in directory `dir` (made when missing) and syncs it: `:ok`
  once it is on disk, else `{:error, reason}`. Options `:max_bytes`, `:keep` (see the moduledoc).
  """
  @spec append(Path.t(), record, keyword) :: :ok | {:error, term}
  def append(dir, record, opts \\ []) do
    with :ok <- check(record) do
      frame = [Log.record(record), Log.end_mark()]
      max = Keyword.get(opts, :max_bytes, @max_bytes)
      keep = Keyword.get(opts, :keep, @keep)

      :global.trans({{__MODULE__, dir}, self()}, fn -> append_locked(dir, frame, max, keep) end, [
        node()
      ])
    end
  end

  # As the journal's appends: the record is written over the end mark that closed the file,
  # with a new end mark after it, so only a file written whole ends with one.
  defp append_locked(dir, frame, max, keep) do
    path = Path.join(dir, @current)
    mark = byte_size(Log.end_mark())

    with :ok <- File.mkdir_p(dir),
         {:ok, size} <- size_after_rotation(dir, path, IO.iodata_length(frame), max, keep),
         {:ok, fd} <- :file.open(path, [:read, :write, :raw, :binary]) do
      result = with :ok <- :file.pwrite(fd, max(size - mark, 0), frame), do: :file.sync(fd)
      :file.close(fd)

      if result == :ok and size == 0,
        do: Vws.CEC.Library.Files.sync_dir(dir),
        else: result
    end
  end

  # a full file, or one whose last append was torn, is set aside before the next append:
  # {:ok, size of the file to append to}
  defp size_after_rotation(dir, path, adding, max, keep) do
    case File.stat(path) do
      {:ok, %{size: 0}} ->
        {:ok, 0}

      {:ok, %{size: size}} ->
        if size + adding - byte_size(Log.end_mark()) > max or not ends_whole?(path, size),
          do: with(:ok <- rotate(dir, keep), do: {:ok, 0}),
          else: {:ok, size}

      {:error, :enoent} ->
        {:ok, 0}

      error ->
        error
    end
  end

  defp ends_whole?(path, size) do
    mark = Log.end_mark()

    with true <- size >= byte_size(mark),
         {:ok, fd} <- :file.open(path, [:read, :raw, :binary]) do
      tail = :file.pread(fd, size - byte_size(mark), byte_size(mark))
      :file.close(fd)
      tail == {:ok, mark}
    else
      _ -> false
    end
  end

  defp rotate(dir, keep) do
    _ = File.rm(Path.join(dir, rotated(keep)))

    for i <- (keep - 1)..1//-1 do
      from = Path.join(dir, rotated(i))
      if File.exists?(from), do: :ok = :file.rename(from, Path.join(dir, rotated(i + 1)))
    end

    with :ok <- :file.rename(Path.join(dir, @current), Path.join(dir, rotated(1))),
         do: Vws.CEC.Library.Files.sync_dir(dir)
  end

  defp rotated(i), do: "transfers.#{i}.log"

  @doc """
  Every record of the history in `dir` (with `newest`, the files holding the newest that many at
  least), oldest first, with what could not be read:
  `%{records: [record], damaged: [%{file, offset, why}]}` — `why` one of `:bad_header`,
  `:bad_checksum`, `:cut_short`, `:no_end_mark` (the frame's) or `:not_a_record` (a whole
  frame whose contents are not a transfer record). Every damaged part is also logged.
  """
  @spec read(Path.t(), pos_integer | nil) :: %{records: [record], damaged: [map]}
  def read(dir, newest \\ nil) do
    files =
      case File.ls(dir) do
        {:ok, names} ->
          names
          |> Enum.flat_map(fn
            @current -> [{0, @current}]
            "transfers." <> rest -> rotation_index(rest)
            _ -> []
          end)
          |> Enum.sort(:desc)
          |> Enum.map(&elem(&1, 1))

        {:error, _} ->
          []
      end

    # newest file first, until `newest` records are read (all files without it)
    {records, damaged} =
      files
      |> Enum.reverse()
      |> Enum.reduce_while({[], []}, fn file, {records, damaged} ->
        acc =
          case File.read(Path.join(dir, file)) do
            {:ok, bin} ->
              {r, d} = parse(bin)
              {r ++ records, Enum.map(d, &Map.put(&1, :file, file)) ++ damaged}

            {:error, reason} ->
              {records, [%{file: file, offset: 0, why: reason} | damaged]}
          end

        if newest && length(elem(acc, 0)) >= newest, do: {:halt, acc}, else: {:cont, acc}
      end)

    for d <- damaged do
      Logger.error(
        "transfer history #{Path.join(dir, d.file)}: bytes from offset #{d.offset} skipped " <>
          "(#{d.why}): a record there cannot be read"
      )
    end

    %{records: records, damaged: damaged}
  end

  defp rotation_index(rest) do
    case Integer.parse(rest) do
      {i, ".log"} when i > 0 -> [{i, "transfers.#{rest}"}]
      _ -> []
    end
  end

  @doc """
  The records of one file's bytes and its damaged parts (`%{offset, why}`), pure. A record is
  taken only when its frame's two CRC-32s hold and it is a whole transfer record.
  """
  @spec parse(binary) :: {[record], [map]}
  def parse(bin) do
    bin
    |> Log.parse()
    |> Enum.reduce({[], []}, fn
      {:record, off, payload}, {records, damaged} ->
        case decode(payload) do
          {:ok, r} -> {[r | records], damaged}
          :error -> {records, [%{offset: off, why: :not_a_record} | damaged]}
        end

      {:kind, off, _kind}, {records, damaged} ->
        {records, [%{offset: off, why: :not_a_record} | damaged]}

      {:damaged, off, why}, {records, damaged} ->
        {records, [%{offset: off, why: why} | damaged]}
    end)
    |> then(fn {r, d} -> {Enum.reverse(r), Enum.reverse(d)} end)
  end

  defp decode(payload) do
    case :erlang.binary_to_term(payload, [:safe]) do
      %{} = r -> if check(r) == :ok, do: {:ok, r}, else: :error
      _ -> :error
    end
  rescue
    ArgumentError -> :error
  end

  defp check(record) when is_map(record) and map_size(record) == @field_count do
    if Enum.all?(@fields, fn {k, ok?} -> Map.has_key?(record, k) and ok?.(record[k]) end),
      do: :ok,
      else: {:error, :not_a_record}
  end

  defp check(_record), do: {:error, :not_a_record}

  @doc false
  def binary_or_nil?(v), do: is_nil(v) or is_binary(v)
  @doc false
  def integer_or_nil?(v), do: is_nil(v) or is_integer(v)
end
