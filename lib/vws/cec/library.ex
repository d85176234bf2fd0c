defmodule Vws.CEC.Library do
  @moduledoc """
  The program library (issues 18 and 30): every workstation's NC programs on disk, each with its
  versions — who or what stored it, when, its size, CRC-16/ARC and SHA-256 digest — kept across
  restarts and crashes. A plain module over files: no process of its own, so MONARCH, SUN_COMM, iex and the
  command-line task (`mix vws.library`, which also works while the workstation is stopped) use
  the same directory side by side.

  ## Where

      <data directory>/library/<workstation id>/      (Vws.Ops.DataDir.library_dir/2)
      ├── 001234.PRO~000001~20261125T090000.123Z~wc~000412~BB3D~<SHA-256, 64 hex>   version 1
      ├── 001234.PRO~000002~20261125T093512.004Z~from+the+machine~000415~1F0C~<SHA-256>
      ├── MACHINE.DIR                      the GE-2000's directory as last read (compare)
      └── .v/
          ├── 001234.PRO~000001 -> ../001234.PRO~000001~…       the version's number, taken
          └── 001234.PRO~000002 -> ../001234.PRO~000002~…

  One flat directory per workstation (decision): listing 10,000 programs is one directory read
  (`bench/library.exs`). A version is a file holding exactly the program's bytes, named
  `<program>~<version>~<stored at, UTC>~<source>~<size>~<CRC>~<SHA-256>` (source's blanks as
  `+`); the name carries what a listing shows, so a listing reads no file (but for versions stored
  before the digest, named without it: their digest is computed from their bytes as they are
  listed).

  **Versions are told apart by content**: by their SHA-256 digest (`digest/1`) — "the same
  program again", "the machine holds version n" — never by size and CRC-16, which different texts
  share (the GE-2000's directory speaks only those: `on_machine/2` says `{:ambiguous, [n]}` when
  versions that differ share them, and a read-back tells).

  **Released or from the machine.** A version whose source is `"from the machine"` (a program
  the operator sent from the control panel) is not released (`released?/1`, the version's
  `origin: :machine`, `released: false`): `:latest` names the newest *released* version, so such
  a version is sent to a machine only by a `DOWNLOAD_GE(nnnnnn.PRO/v)` naming it, until
  `release/4` stores its bytes as a new, released version.

  **Program names** are the GE-2000's file names, `nnnnnn.PRO` or `nnnnnn.GSU` (a library
  program is the file it becomes on the machine); `1234`, `001234` and `o1234.pro` are read as
  `001234.PRO`. Anything else — a path, `..`, a `~` — is refused (`{:error, :bad_name}`), so a
  name never leaves the directory.

  **Crash-safe, whole or nothing.** `store/4` writes the bytes to a hidden temporary file and
  syncs it; then takes the next version number by creating the symbolic link
  `.v/<program>~<version>` (which fails when that number is taken — by another process of this
  node, or by `mix vws.library` in another OS process — and the next number is tried: no two
  stores ever get one number); then renames the temporary file to its version name and syncs the
  directory. A version is visible only under its full name, which appears by the rename with
  all its bytes on disk: a crash leaves either no version or a whole one (at worst a number
  taken by a store that never finished: that number is then skipped). Reading a version checks
  its size, CRC and digest against its name: a file damaged on disk reads `{:error, :damaged}`.

  **Compare** (`compare/1`): MONARCH records the machine's directory here each time it reads it
  (`record_machine/2`: after every DOWNLOAD_GE, on `COMPARE_GE`, `Vws.Partitions.Monarch.compare/2`);
  a program is then `same` (the entry's size and CRC are those of versions holding one text:
  which), `ambiguous` (of versions that differ), `differs` or `absent` on the machine; `unknown`
  before any directory was read. A full read-back (`Vws.Partitions.Monarch.compare/2`,
  `COMPARE_GE(nnnnnn.PRO)`) takes the digest of every byte and names the version that has it.

  ## Parts

  This module is the store's interface; the parts it delegates to are pure or plain file work:
  `Vws.CEC.Library.Version` (digests, released or not, where the machine stands),
  `Vws.CEC.Library.Files` (version file names, number links, files written whole) and
  `Vws.CEC.Library.Check` (is it an NC program). It prints nothing: the words and tables for
  people are `Vws.Ops.LibraryText`'s (`print_compare/1`, `format_diff/1`, …).

  ## Used from

  Every function takes the workstation's id (a running workstation started with `library:`,
  `Vws.CEC.Workstation`) or `{:dir, path}` (any library directory, e.g. that of a stopped workstation).

      iex> dir = Path.join(System.tmp_dir!(), "vws-lib-doc-\#{System.unique_integer([:positive])}")
      iex> {:ok, v} = Vws.CEC.Library.store({:dir, dir}, "1234", "%\\nO1234\\nM30\\n%\\n", source: "iex")
      iex> {v.name, v.version, v.size, v.source}
      {"001234.PRO", 1, 14, "iex"}
      iex> {:ok, "%\\nO1234\\nM30\\n%\\n", _} = Vws.CEC.Library.read({:dir, dir}, "001234.PRO")
      iex> File.rm_rf!(dir) |> is_list()
      true
  """

  require Logger

  @machine "MACHINE.DIR"

  alias Vws.CEC.Library.{Check, Diff, Files, History, Search, Version, Workflow}

  @typedoc "A workstation id, or `{:dir, path}` for a library directory itself."
  @type lib :: term | {:dir, Path.t()}

  @typedoc "One stored version."
  @type version :: Version.t()

  @type on_machine :: Version.on_machine()

  ## Where

  @doc """
  Makes `dir` the library of workstation `ws` for as long as the calling process lives (the
  workstation's supervisor calls it as it starts; `nil` for none), and removes the temporary
  files of stores that crashed more than an hour ago (`tidy/2`).
  """
  @spec register(term, Path.t() | nil) :: :ok
  def register(_ws, nil), do: :ok

  def register(ws, dir) do
    {:ok, _} = Registry.register(Vws.Registry, {ws, :library}, Path.expand(dir))

    with {:error, reason} <- tidy({:dir, dir}) do
      Logger.warning("program library #{dir}: not tidied (#{inspect(reason)})")
    end

    :ok
  end

  @doc "The library directory: `{:ok, dir}` or `{:error, :no_library}` (a workstation without one)."
  @spec dir(lib) :: {:ok, Path.t()} | {:error, :no_library}
  def dir({:dir, dir}), do: {:ok, Path.expand(dir)}

  def dir(ws) do
    case Registry.lookup(Vws.Registry, {ws, :library}) do
      [{_pid, dir}] -> {:ok, dir}
      [] -> {:error, :no_library}
    end
  end

  @doc "True when `lib` has a library (a directory given, or a workstation started with one)."
  @spec enabled?(lib) :: boolean
  def enabled?(lib), do: match?({:ok, _}, dir(lib))

  @doc """
  The largest program the library keeps: 64 MiB, for the longest drip feed (the machine keeps
  none of it). What the GE-2000 *stores*, 999,999 bytes, is `Vws.Links.DNC.Program.check_size/1`'s:
  DOWNLOAD_GE or a remote request of a larger version ends `ERROR PROGRAM TOO LARGE`, none sent.
  """
  @spec max_bytes() :: pos_integer
  defdelegate max_bytes, to: Check

  ## Names

  @doc """
  A program name as the library keeps it: `{:ok, "nnnnnn.PRO" | "nnnnnn.GSU"}` or
  `{:error, :bad_name}`.

      iex> Vws.CEC.Library.name("1234")
      {:ok, "001234.PRO"}
      iex> Vws.CEC.Library.name("o77.gsu")
      {:ok, "000077.GSU"}
      iex> Vws.CEC.Library.name("../../etc/passwd")
      {:error, :bad_name}
  """
  @spec name(term) :: {:ok, String.t()} | {:error, :bad_name}
  def name(name) when is_binary(name) and byte_size(name) <= 16 do
    case Regex.run(~r/^[Oo:]?(\d{1,6})(?:\.(PRO|GSU))?$/i, String.trim(name)) do
      [_, digits] -> {:ok, String.pad_leading(digits, 6, "0") <> ".PRO"}
      [_, digits, ext] -> {:ok, String.pad_leading(digits, 6, "0") <> "." <> String.upcase(ext)}
      nil -> {:error, :bad_name}
    end
  end

  def name(n) when is_integer(n) and n in 0..999_999, do: name(Integer.to_string(n))
  def name(_), do: {:error, :bad_name}

  ## Storing

  @doc """
  Stores `bytes` as the next version of program `name`: `{:ok, version}`, or `{:error, reason}`
  (`:bad_name`, `:bad_source`, `:too_large`, `:no_library`, a file error) and nothing stored.

  Options: `:source` — who or what stored it (`"wc"`, `"cli"`, `"from the machine"`, `"iex"`;
  default `"iex"`; lower-case letters, digits, blanks, `.`, `-`, `_`, at most 32; a version
  whose source is `"from the machine"` is not released, `released?/1`), `:state` (`:draft`: a
  draft, never sent by `DOWNLOAD_GE(nnnnnn.PRO)`; default released), `:comment`, `:at` (a `DateTime`,
  default now), `:only_if_changed` — when the latest released version holds exactly these bytes
  (the same SHA-256 digest, and its file reads whole), store nothing and answer that version
  (default false), `:only_if_new` — likewise when any version holds them (the one `same_as/2`
  names).
  """
  @spec store(lib, term, binary, keyword) :: {:ok, version} | {:error, term}
  def store(lib, name, bytes, opts \\ []) when is_binary(bytes) do
    dedupe =
      cond do
        Keyword.get(opts, :only_if_new, false) -> :any
        Keyword.get(opts, :only_if_changed, false) -> :latest
        true -> nil
      end

    case dedupe && existing(lib, name, digest(bytes), dedupe) do
      {:ok, v} -> {:ok, v}
      _ -> with {:ok, v} <- store_new(lib, name, bytes, opts), do: initial_state(lib, v, opts)
    end
  end

  # a version stored as a draft, or with a comment, gets its state file (Workflow)
  defp initial_state(lib, v, opts) do
    draft? = opts[:state] == :draft

    if draft? or opts[:comment] do
      {:ok, dir} = dir(lib)
      by = Keyword.get(opts, :source, "iex")

      with {:ok, s} <-
             Workflow.change(dir, v, by, "stored", fn s ->
               %{s | state: if(draft?, do: :draft, else: s.state), comment: opts[:comment]}
             end),
           do:
             {:ok,
              Map.merge(v, %{state: s.state, released: s.state == :released, comment: s.comment})}
    else
      {:ok, Map.merge(v, %{state: Workflow.default(v).state, comment: nil})}
    end
  end

  # The version that already holds bytes of this digest (the latest released one, or any:
  # same_as/2), when its file reads whole.
  defp existing(lib, name, digest, which) do
    with {:ok, vs} <- versions(lib, name),
         {:ok, v} <-
           (case which do
              :latest -> latest_released(vs)
              :any -> same_as(vs, digest)
            end),
         true <- v.digest == digest,
         {:ok, _bytes, v} <- read(lib, name, v.version) do
      {:ok, v}
    end
  end

  defp store_new(lib, name, bytes, opts) do
    source = Keyword.get(opts, :source, "iex")
    at = Keyword.get_lazy(opts, :at, &DateTime.utc_now/0) |> DateTime.truncate(:millisecond)

    with {:ok, dir} <- dir(lib),
         {:ok, name} <- name(name),
         :ok <- check_source(source),
         :ok <- if(byte_size(bytes) <= max_bytes(), do: :ok, else: {:error, :too_large}),
         :ok <- File.mkdir_p(Files.numbers_dir(dir)),
         tmp = Files.tmp_path(dir, name),
         :ok <- Files.write_synced(tmp, bytes) do
      v =
        Version.with_origin(%{
          name: name,
          version: nil,
          at: at,
          source: source,
          size: byte_size(bytes),
          crc: Vws.Codecs.CRC16.compute(bytes),
          digest: digest(bytes),
          file: nil
        })

      case Files.take_number(dir, v, Files.first_free(dir, name)) do
        {:ok, v} ->
          with :ok <- Files.rename_or_remove(tmp, Path.join(dir, v.file)),
               :ok <- Files.sync_dir(dir),
               do: {:ok, v}

        error ->
          File.rm(tmp)
          error
      end
    end
  end

  @doc """
  The SHA-256 digest of a program's bytes, as the library names versions by it (64 lower-case
  hexadecimal digits). Two versions hold the same bytes exactly when their digests are equal;
  size and CRC-16 are kept only because the GE-2000's directory speaks them.

      iex> Vws.CEC.Library.digest("") |> String.slice(0, 16)
      "e3b0c44298fc1c14"
  """
  @spec digest(binary) :: String.t()
  defdelegate digest(bytes), to: Version

  @doc """
  True for a released version — one `:latest` may name and `DOWNLOAD_GE(nnnnnn.PRO/v)` sends:
  its workflow state (`Vws.CEC.Library.Workflow`) says so; without one, every version but those
  the operator sent from the machine (source `"from the machine"`), which are drafts until
  `release/4`. A draft goes to a machine only by `DOWNLOAD_GE(nnnnnn.PRO/v/FORCE)`.
  """
  @spec released?(map) :: boolean
  defdelegate released?(version), to: Version

  @doc """
  Releases version `which` of `name`. A draft stored in the library (`store/4` with `state:
  :draft`, or unreleased) is released in place; a version from the machine has its bytes stored
  as a new, released version (source `"<source> release of v<n>"`, `opts[:source]` default
  `"iex"`) — unless the latest released version already holds exactly these bytes: then that
  version is the answer. `{:ok, version}` or `{:error, reason}` (`:not_found`, `:damaged`, …).
  """
  @spec release(lib, term, pos_integer | :latest | :newest, keyword) ::
          {:ok, version} | {:error, term}
  def release(lib, name, which, opts \\ []) do
    with {:ok, bytes, v} <- read(lib, name, which),
         :copy <- release_in_place(lib, v, opts) do
      source = "#{Keyword.get(opts, :source, "iex")} release of v#{v.version}"
      store(lib, name, bytes, source: source, only_if_changed: true)
    end
  end

  defp release_in_place(lib, v, opts) do
    if v.source == "from the machine" do
      :copy
    else
      set_state(lib, v, opts, "released", &%{&1 | state: :released})
    end
  end

  defp set_state(lib, v, opts, what, fun) do
    with {:ok, dir} <- dir(lib),
         {:ok, s} <- Workflow.change(dir, v, Keyword.get(opts, :source, "iex"), what, fun),
         do:
           {:ok,
            Map.merge(v, %{state: s.state, released: s.state == :released, comment: s.comment})}
  end

  @doc """
  Makes version `n` of `name` a draft (`DOWNLOAD_GE(nnnnnn.PRO)` no longer sends it; `:latest`
  names the released version before it). `{:ok, version}` or `{:error, reason}`.
  """
  @spec unrelease(lib, term, pos_integer, keyword) :: {:ok, version} | {:error, term}
  def unrelease(lib, name, n, opts \\ []) do
    with {:ok, v} <- version(lib, name, n),
         do: set_state(lib, v, opts, "unreleased", &%{&1 | state: :draft})
  end

  @doc "Sets the comment of version `n` of `name` (at most 200 printable characters)."
  @spec comment(lib, term, pos_integer, String.t(), keyword) :: {:ok, version} | {:error, term}
  def comment(lib, name, n, text, opts \\ []) do
    with true <-
           (String.printable?(text) and String.length(text) <= 200) || {:error, :bad_comment},
         {:ok, v} <- version(lib, name, n),
         do: set_state(lib, v, opts, "comment", &%{&1 | comment: text})
  end

  @doc """
  Deletes version `n` of `name`, keeping its tombstone (`tombstones/2`: what it was, when and
  by whom it was deleted, `why`): it leaves every listing, search, compare and `DOWNLOAD_GE`, its
  number is never given again, and the transfer history still names it. Its bytes stay on disk
  (`read/4` with `deleted: true`): the journal may name it as the NC file's program.
  `{:ok, tombstone}` or `{:error, reason}`.
  """
  @spec delete(lib, term, pos_integer, keyword) :: {:ok, map} | {:error, term}
  def delete(lib, name, n, opts \\ []) do
    with {:ok, dir} <- dir(lib),
         {:ok, v} <- version(lib, name, n),
         gone = Map.take(v, [:size, :crc, :digest, :source, :at, :state]),
         why = opts[:why] || "deleted",
         {:ok, s} <-
           Workflow.change(dir, v, Keyword.get(opts, :source, "iex"), why, fn s ->
             %{s | state: :deleted, deleted: gone}
           end) do
      {:ok, Map.merge(s, %{name: v.name, version: v.version})}
    end
  end

  @doc "The tombstones of deleted versions (of `name` only, when given), by name and version."
  @spec tombstones(lib, term) :: {:ok, [map]} | {:error, term}
  def tombstones(lib, name \\ nil) do
    with {:ok, dir} <- dir(lib),
         {:ok, name} <- if(name, do: name(name), else: {:ok, nil}),
         do: {:ok, Workflow.tombstones(dir, name)}
  end

  @doc """
  Finds versions by program number, comment and text (case-insensitive): `{:ok, [%{name,
  version, matched: [:name | :comment | :text], line}]}` — `line` the first line of its text that
  holds `query` (nil when only its name or comment did). Option `:in` (default all three).
  """
  @spec search(lib, String.t(), keyword) :: {:ok, [map]} | {:error, term}
  def search(lib, query, opts \\ []) do
    where = Keyword.get(opts, :in, [:name, :comment, :text])

    with {:ok, programs} <- list(lib) do
      {:ok, Search.run(programs, query, where, &read(lib, &1, &2))}
    end
  end

  ## What the machine holds: read-backs and line diffs (issue 27)

  @doc """
  Keeps the bytes a read-back (`COMPARE_GE(nnnnnn.PRO)`) found on the machine, whole, in
  `machine/<name>` of the library: what `diff_machine/3` compares.
  """
  @spec record_read_back(lib, term, binary) :: :ok | {:error, term}
  def record_read_back(lib, name, bytes) do
    with {:ok, dir} <- dir(lib),
         {:ok, name} <- name(name),
         machine = Path.join(dir, "machine"),
         :ok <- File.mkdir_p(machine),
         :ok <- Files.write_whole(Files.tmp_path(machine, name), Path.join(machine, name), bytes),
         do: Files.sync_dir(machine)
  end

  @doc """
  The line diff of version `which` of `name` (default the latest released, else the newest)
  against what the machine held at the last read-back: `{:ok, %{version, read_at, diff,
  summary}}` (`Vws.CEC.Library.Diff`), or `{:error, :not_read_back}` when none was made.
  """
  @spec diff_machine(lib, term, pos_integer | :latest) :: {:ok, map} | {:error, term}
  def diff_machine(lib, name, which \\ :latest) do
    with {:ok, dir} <- dir(lib),
         {:ok, name} <- name(name),
         path = Path.join([dir, "machine", name]),
         {:ok, machine} <- File.read(path) |> not_read_back(),
         {:ok, %{mtime: mtime}} <- File.stat(path, time: :posix),
         {:ok, v} <- reference_version(lib, name, which),
         {:ok, text, v} <- read(lib, name, v.version) do
      diff = Diff.lines(text, machine)
      read_at = DateTime.from_unix!(mtime)
      {:ok, %{version: v, read_at: read_at, diff: diff, summary: Diff.summary(diff)}}
    end
  end

  defp not_read_back({:error, :enoent}), do: {:error, :not_read_back}
  defp not_read_back(other), do: other

  # what a compare is shown against: version n; else the latest released, or the newest
  defp reference_version(lib, name, :latest) do
    with {:error, :not_released} <- version(lib, name, :latest), do: version(lib, name, :newest)
  end

  defp reference_version(lib, name, n), do: version(lib, name, n)

  defp check_source(source) when is_binary(source) do
    # \A…\z, not ^…$: $ also matches before a final newline, and "shop\n" is no label
    if source =~ ~r/\A[a-z0-9][a-z0-9 ._-]{0,31}\z/, do: :ok, else: {:error, :bad_source}
  end

  defp check_source(_), do: {:error, :bad_source}

  @doc """
  DOWNLOAD_HP's program (the lines the WC sent) as the next version of its program (named by its
  program number), source `"wc"` — unless the latest released version holds exactly these bytes
  (the same SHA-256 digest: the same program downloaded again is not a new version):
  `{:ok, version}` (the one stored, or the one that holds these bytes already); `:ok` when the
  workstation has no library, or the program has no program number (then it is the NC file
  only, as in the seed); or `{:error, {:library, reason}}`: SUN_COMM then ends DOWNLOAD_HP with
  an error and keeps the old NC file.
  """
  @spec store_download(lib, [binary]) :: {:ok, version} | :ok | {:error, {:library, term}}
  def store_download(lib, lines) do
    with true <- enabled?(lib),
         {:ok, name} <- Vws.Links.DNC.Program.file_name(lines),
         {:ok, v} <-
           store(lib, name, Vws.Links.DNC.Program.to_text(lines),
             source: "wc",
             only_if_changed: true
           ) do
      Logger.info("program library: #{v.name} version #{v.version} stored (#{v.size} bytes)")
      {:ok, v}
    else
      false -> :ok
      {:error, reason} when reason in [:no_program_number, :bad_program_number] -> :ok
      {:error, reason} -> {:error, {:library, reason}}
    end
  end

  @doc """
  Stores the file at `path` as the next version (`store/4`) when it is an NC program
  (`check_program/1`): the program name is `opts[:name]`, else the program number of its text
  (`O1234` → `001234.PRO`). Source default `"cli"`.

  `{:ok, version}` when stored; `{:same, version}` when the latest released version already holds
  exactly these bytes (nothing stored); `{:error, {:not_a_program, why}}` (`Vws.Ops.LibraryText.program_refusal/1`
  says it in words), `{:error, {:not_a_file, type}}` or another `store/4` error, nothing stored.
  """
  @spec import_file(lib, Path.t(), keyword) ::
          {:ok, version} | {:same, version} | {:error, term}
  def import_file(lib, path, opts \\ []) do
    with {:ok, %{size: size, type: :regular}} <- File.stat(path),
         :ok <- check_size(size),
         {:ok, bytes} <- File.read(path),
         :ok <- check_program(bytes),
         {:ok, name} <- import_name(opts[:name], bytes) do
      case existing(lib, name, digest(bytes), :latest) do
        {:ok, v} -> {:same, v}
        _ -> store(lib, name, bytes, Keyword.put_new(opts, :source, "cli"))
      end
    else
      {:ok, %{type: type}} -> {:error, {:not_a_file, type}}
      error -> error
    end
  end

  # what the library keeps (max_bytes/0), checked before the file is read
  defp check_size(size),
    do: if(size > max_bytes(), do: {:error, {:not_a_program, {:too_large, size}}}, else: :ok)

  @doc """
  Whether `bytes` are an NC program the library may keep and the links can carry: `:ok`, or
  `{:error, {:not_a_program, why}}` with `why` one of `{:too_large, bytes}` (over `max_bytes/0`,
  64 MiB: what the library keeps; the machine's own 999,999 is checked as a program is sent to
  be stored, PROTOCOLS.md §2 "Program size limit"), `{:binary, offset}` (a NUL byte, or not text),
  `{:control, byte, line}` (a control character other than TAB, CR and LF), `:no_start`
  (the first line is not `%`), `:no_end` (the last line is not `%`, or it has no LF:
  `Vws.Links.DNC.Program.complete?/1`), `:no_program_number` (the first line after `%` is not an
  `O` word, or `:` in EIA) or `:bad_program_number` (more than six digits).

      iex> Vws.CEC.Library.check_program("%\\nO1234\\nN10 G00 X0\\nM30\\n%\\n")
      :ok
      iex> Vws.CEC.Library.check_program("import os\\nprint(os.getcwd())\\n")
      {:error, {:not_a_program, :no_start}}
      iex> Vws.CEC.Library.check_program("%\\nN10 G00\\n%\\n")
      {:error, {:not_a_program, :no_program_number}}
  """
  @spec check_program(binary) :: :ok | {:error, {:not_a_program, term}}
  defdelegate check_program(bytes), to: Check, as: :program

  defp import_name(nil, bytes) do
    case Vws.Links.DNC.Program.file_name(bytes) do
      {:ok, name} -> {:ok, name}
      {:error, _} -> {:error, :no_program_number}
    end
  end

  defp import_name(name, _bytes), do: {:ok, name}

  @doc "Writes version `version` (default the latest) of `name` to `path` (whole: temp, sync, rename)."
  @spec export(lib, term, pos_integer | :latest, Path.t()) :: {:ok, version} | {:error, term}
  def export(lib, name, version \\ :latest, path) do
    with {:ok, bytes, v} <- read(lib, name, version) do
      tmp = path <> ".tmp-#{:os.getpid()}-#{System.unique_integer([:positive])}"
      with :ok <- Files.write_whole(tmp, path, bytes), do: {:ok, v}
    end
  end

  ## Reading

  @doc """
  Every program with its versions, oldest version first, programs sorted by name:
  `{:ok, [%{name, versions: [version]}]}` (an empty list when nothing was stored yet).
  """
  @spec list(lib) :: {:ok, [%{name: String.t(), versions: [version]}]} | {:error, term}
  def list(lib) do
    with {:ok, versions} <- all_versions(lib) do
      programs =
        versions
        |> Enum.group_by(& &1.name)
        |> Enum.map(fn {name, vs} -> %{name: name, versions: Enum.sort_by(vs, & &1.version)} end)
        |> Enum.sort_by(& &1.name)

      {:ok, programs}
    end
  end

  @doc "The versions of program `name`, oldest first (`{:error, :not_found}` when it has none)."
  @spec versions(lib, term) :: {:ok, [version]} | {:error, term}
  def versions(lib, name) do
    with {:ok, dir} <- dir(lib),
         {:ok, name} <- name(name),
         {:ok, files} <- Files.ls(dir) do
      case files
           |> Enum.filter(&String.starts_with?(&1, name <> "~"))
           |> Files.parse_files()
           |> Files.with_digests(dir)
           |> Workflow.apply_states(dir) do
        [] -> {:error, :not_found}
        vs -> {:ok, Enum.sort_by(vs, & &1.version)}
      end
    end
  end

  @doc """
  One version of `name`: `{:ok, version}` or `{:error, :not_found}`. `:latest` (the default) is
  the newest *released* version (`released?/1`) — `{:error, :not_released}` when every version
  came from the machine; `:newest` the newest of all; `n` version n.
  """
  @spec version(lib, term, pos_integer | :latest | :newest) :: {:ok, version} | {:error, term}
  def version(lib, name, which \\ :latest)

  def version(lib, name, :latest) do
    with {:ok, vs} <- versions(lib, name), do: latest_released(vs)
  end

  def version(lib, name, :newest) do
    with {:ok, vs} <- versions(lib, name), do: {:ok, List.last(vs)}
  end

  def version(lib, name, n) when is_integer(n) and n > 0 do
    with {:ok, dir} <- dir(lib), {:ok, name} <- name(name) do
      # the number's link names the version's file: no directory listing needed
      with {:ok, target} <- :file.read_link(Files.number_link(dir, name, n)),
           [v] <- Files.parse_files([target |> to_string() |> Path.basename()]),
           true <- v.name == name and v.version == n,
           true <- File.regular?(Path.join(dir, v.file)),
           [v] <- Workflow.apply_states(Files.with_digests([v], dir), dir) do
        {:ok, v}
      else
        _ ->
          if match?({:ok, %{state: :deleted}}, Workflow.state(dir, name, n)),
            do: {:error, :deleted},
            else: {:error, :not_found}
      end
    end
  end

  def version(_lib, _name, _n), do: {:error, :not_found}

  @doc """
  The newest released version among `versions` (oldest first, as `versions/2` gives them):
  `{:ok, version}`, or `{:error, :not_released}` when there is none.
  """
  @spec latest_released([version]) :: {:ok, version} | {:error, :not_released}
  defdelegate latest_released(versions), to: Version

  @doc """
  The version among `versions` that holds the bytes of SHA-256 `digest` (`digest/1`): the newest
  released one with it, else the newest with it — `{:ok, version}` or `:none`.
  """
  @spec same_as([version], String.t() | nil) :: {:ok, version} | :none
  defdelegate same_as(versions, digest), to: Version

  @doc """
  The bytes of a version (`:latest` by default, see `version/3`): `{:ok, bytes, version}`;
  `{:error, :damaged}` when the file's size, CRC or SHA-256 digest is not the one it was stored
  with; `{:error, :deleted}` for a deleted version, unless `opts[:deleted]` (what the journal's
  reference to the NC file's version needs: a deleted version's bytes stay on disk).
  """
  @spec read(lib, term, pos_integer | :latest | :newest, keyword) ::
          {:ok, binary, version} | {:error, term}
  def read(lib, name, which \\ :latest, opts \\ []) do
    with {:ok, dir} <- dir(lib),
         {:ok, v} <- version_to_read(lib, dir, name, which, opts[:deleted]),
         {:ok, bytes} <- File.read(Path.join(dir, v.file)) do
      if whole?(bytes, v), do: {:ok, bytes, v}, else: {:error, :damaged}
    end
  end

  defp version_to_read(lib, dir, name, n, true) when is_integer(n) do
    with {:error, :deleted} <- version(lib, name, n),
         {:ok, name} <- name(name),
         {:ok, target} <- :file.read_link(Files.number_link(dir, name, n)),
         [v] <- Files.parse_files([target |> to_string() |> Path.basename()]) do
      {:ok, Map.merge(hd(Files.with_digests([v], dir)), %{state: :deleted, released: false})}
    else
      {:error, _} = error -> error
      {:ok, v} -> {:ok, v}
      _ -> {:error, :not_found}
    end
  end

  defp version_to_read(lib, _dir, name, which, _deleted), do: version(lib, name, which)

  defp whole?(bytes, v) do
    byte_size(bytes) == v.size and Vws.Codecs.CRC16.compute(bytes) == v.crc and
      v.digest != nil and digest(bytes) == v.digest
  end

  @doc """
  The differences between two versions of `name`, line by line: `{:ok, [{:eq | :del | :ins,
  [line]}]}` (`List.myers_difference/2`); `Vws.Ops.LibraryText.format_diff/1` prints it.
  """
  @spec diff(lib, term, pos_integer | :latest, pos_integer | :latest) ::
          {:ok, [{:eq | :del | :ins, [binary]}]} | {:error, term}
  def diff(lib, name, a, b) do
    with {:ok, text_a, _} <- read(lib, name, a),
         {:ok, text_b, _} <- read(lib, name, b) do
      {:ok, Diff.lines(text_a, text_b)}
    end
  end

  ## The machine's directory and the compare

  @doc """
  Records the GE-2000's directory as just read (`%{file name => %{size, crc}}`, as
  `Vws.Links.DNC.Report.parse_directory/1` gives it), whole or not at all, in `MACHINE.DIR`.
  """
  @spec record_machine(lib, %{String.t() => map}, DateTime.t()) :: :ok | {:error, term}
  def record_machine(lib, entries, at \\ DateTime.utc_now()) do
    with {:ok, dir} <- dir(lib), :ok <- File.mkdir_p(dir) do
      text = [
        "READ ",
        DateTime.to_iso8601(DateTime.truncate(at, :millisecond)),
        ?\n,
        for {name, e} <- Enum.sort(entries) do
          directory_line(name, e)
        end
      ]

      path = Path.join(dir, @machine)

      with :ok <- Files.write_whole(Files.tmp_path(dir, @machine), path, text),
           do: Files.sync_dir(dir)
    end
  end

  # what the machine's directory said of one file, as it is recorded (and read back by
  # Report.parse_directory/1): a line it could not read stays unreadable
  defp directory_line(name, :unreadable), do: [name, " UNREADABLE\n"]

  defp directory_line(name, e),
    do: [
      name,
      ?\s,
      Files.pad(e.size, 6),
      ?\s,
      String.pad_leading(Integer.to_string(e.crc, 16), 4, "0"),
      ?\n
    ]

  @doc "The machine's directory as last recorded: `{:ok, %{read_at, entries}}`, `:none`, or an error."
  @spec machine(lib) ::
          {:ok, %{read_at: DateTime.t(), entries: %{String.t() => map}}} | :none | {:error, term}
  def machine(lib) do
    with {:ok, dir} <- dir(lib) do
      case File.read(Path.join(dir, @machine)) do
        {:ok, text} ->
          with ["READ " <> at, rest] <- String.split(text, "\n", parts: 2),
               {:ok, at, 0} <- DateTime.from_iso8601(at),
               {:ok, entries} <- Vws.Links.DNC.Report.parse_directory(rest) do
            {:ok, %{read_at: at, entries: entries}}
          else
            _ -> {:error, :damaged}
          end

        {:error, :enoent} ->
          :none

        error ->
          error
      end
    end
  end

  @doc """
  Where the machine stands for one program, from its versions and the machine's directory
  entry (nil when the directory has none; `:unknown` for no directory read).

  The directory speaks only size and CRC-16, which different texts may share: the entry names a
  version (`{:same, n}`: `same_as/2` of their digest) only when every version with its size and
  CRC holds the same bytes (the same SHA-256 digest); when versions with different bytes match
  it, it is `{:ambiguous, [n]}` — only reading the program back (`COMPARE_GE(nnnnnn.PRO)`,
  `Vws.Partitions.Monarch.compare/2`) tells which, if any, the machine holds.

      iex> v = %{version: 2, size: 9, crc: 0xBB3D, digest: "aa", source: "wc"}
      iex> Vws.CEC.Library.on_machine([v], %{size: 9, crc: 0xBB3D})
      {:same, 2}
      iex> Vws.CEC.Library.on_machine([v], %{size: 9, crc: 0x1234})
      :differs
      iex> Vws.CEC.Library.on_machine([v], nil)
      :absent
      iex> Vws.CEC.Library.on_machine([%{v | version: 1, digest: "bb"}, v], %{size: 9, crc: 0xBB3D})
      {:ambiguous, [1, 2]}
  """
  @spec on_machine([map], map | nil | :unknown | :unreadable) :: on_machine
  defdelegate on_machine(versions, entry), to: Version

  @doc """
  Every program with its versions and where it stands on the machine, from the directory last
  recorded: `{:ok, %{read_at: DateTime | nil, programs: [%{name, latest, newest, versions,
  on_machine}], machine_only: [file name]}}` — `latest` the newest released version (what
  `DOWNLOAD_GE(nnnnnn.PRO)` sends; nil when every version came from the machine), `newest` the
  newest of all, `machine_only` the machine's files the library does not have.
  """
  @spec compare(lib) :: {:ok, map} | {:error, term}
  def compare(lib) do
    with {:ok, programs} <- list(lib) do
      {read_at, entries} =
        case machine(lib) do
          {:ok, m} -> {m.read_at, m.entries}
          _ -> {nil, :unknown}
        end

      rows =
        for p <- programs do
          entry = if entries == :unknown, do: :unknown, else: Map.get(entries, p.name)

          %{
            name: p.name,
            versions: p.versions,
            latest:
              case latest_released(p.versions) do
                {:ok, v} -> v
                {:error, :not_released} -> nil
              end,
            newest: List.last(p.versions),
            on_machine: on_machine(p.versions, entry)
          }
        end

      names = MapSet.new(programs, & &1.name)

      machine_only =
        if entries == :unknown,
          do: [],
          else:
            entries
            |> Map.keys()
            |> Enum.reject(&MapSet.member?(names, &1))
            |> Enum.sort()

      {:ok, %{read_at: read_at, programs: rows, machine_only: machine_only}}
    end
  end

  @doc """
  What a version is, in words, for listings: `"released"`, `"from the machine, not
  released"` or `"draft, not released"`.
  """
  @spec release_text(map) :: String.t()
  def release_text(v) do
    cond do
      released?(v) -> "released"
      v.source == "from the machine" -> "from the machine, not released"
      true -> "draft, not released"
    end
  end

  ## Files

  defp all_versions(lib) do
    with {:ok, dir} <- dir(lib) do
      case Files.ls(dir) do
        {:ok, files} ->
          {:ok,
           files |> Files.parse_files() |> Files.with_digests(dir) |> Workflow.apply_states(dir)}

        error ->
          error
      end
    end
  end

  ## Transfer history (issue 27)

  @doc """
  Records one transfer in the library's history (`Vws.CEC.Library.History`, synced before
  `:ok`): `fields` as `History.new/1` takes them. `{:error, :no_library}` without a library.
  """
  @spec record_transfer(lib, map | keyword) :: :ok | {:error, term}
  def record_transfer(lib, fields) do
    with {:ok, dir} <- dir(lib), do: History.append(history_dir(dir), History.new(fields))
  end

  @doc """
  The transfer history, newest first: `{:ok, %{records: [record], damaged: [%{file, offset,
  why}]}}` (damaged parts are skipped and logged, never read as a record). Options:
  `:program` (a program name: only its transfers), `:limit` (the newest n).
  """
  @spec history(lib, keyword) ::
          {:ok, %{records: [History.record()], damaged: [map]}} | {:error, term}
  def history(lib, opts \\ []) do
    with {:ok, dir} <- dir(lib),
         {:ok, program} <-
           (case opts[:program] do
              nil -> {:ok, nil}
              p -> name(p)
            end) do
      # the newest files only, when they are enough
      newest = if program == nil, do: opts[:limit]
      %{records: records, damaged: damaged} = History.read(history_dir(dir), newest)

      records =
        records
        |> Enum.reverse()
        |> Enum.filter(&(program == nil or &1.program == program))
        |> then(&if(opts[:limit], do: Enum.take(&1, opts[:limit]), else: &1))

      {:ok, %{records: records, damaged: damaged}}
    end
  end

  @doc "Where the transfer history of library directory `dir` lives."
  @spec history_dir(Path.t()) :: Path.t()
  def history_dir(dir), do: Path.join(dir, "history")

  @doc """
  Removes temporary files left by stores that crashed (older than `min_age_s`, default one hour:
  a younger one may belong to a store in progress in another process).
  """
  @spec tidy(lib, non_neg_integer) :: :ok | {:error, term}
  def tidy(lib, min_age_s \\ 3600) do
    with {:ok, dir} <- dir(lib), {:ok, files} <- Files.ls(dir) do
      limit = System.os_time(:second) - min_age_s

      # (the workflow's state files and the machine's read-backs are written the same way)
      more =
        for sub <- [".state", "machine"],
            {:ok, names} <- [Files.ls(Path.join(dir, sub))],
            name <- names,
            do: Path.join(sub, name)

      for file <- files ++ more, Files.tmp?(Path.basename(file)) do
        path = Path.join(dir, file)

        case File.stat(path, time: :posix) do
          {:ok, %{mtime: mtime}} when mtime <= limit -> File.rm(path)
          _ -> :ok
        end
      end

      :ok
    end
  end
end
