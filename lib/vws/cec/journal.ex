defmodule Vws.CEC.Journal do
  @moduledoc """
  The workstation's durable command journal: durable or refused, never in between; a restart
  restores every status it can, and says so of the rest.

  Every accepted command string and every command-status change is written and synced to disk
  before SUN_COMM acknowledges the string or the mailbox shows the status, so a WC that asks the
  status of any command it sent gets the true answer even after the workstation — or the whole
  node — restarted.

  ## Records

    * `{:string, seq, line, [{partition, number}]}` — a command string SUN_COMM accepted (before `05A`)
    * `{:status, partition, number, status, text}` — a command dispatched (its CMD_IN too)
    * `{:status, partition, number, status}` — a command status written outright (a rule, BUSY)
    * `{:finish, partition, number, status}` — a command ended: applied only while the status
      location still shows `number`, exactly as `Vws.CEC.Mailbox.finish/4` does
    * `{:unknown_status, letter, number, status}` — a command of a set letter the CEC does not
      know, refused by rule 5 (`Vws.CEC.Mailbox.put_unknown_status/4`)
    * `{:lease, volume, holder, reasons}` — a work-volume lease (`Vws.CEC.Interlock`) taken or
      changed, `reasons` `[]` when it ended: written before the lease counts
    * `{:snapshot, state}` — the whole restorable state, the first record of the file

  Each is one frame of `Vws.CEC.Journal.Log` in the file `journal.log`: its own CRC-32 over the
  header and over the record, and an end mark after the last record. `Vws.CEC.Journal.Replay`
  checks every frame's checksums and every record's shape before it applies it.

  The journal process writes every record itself (the callers wait for it, `record/2`): it keeps
  the state its records add up to, so a snapshot is exactly what the records it replaces give.
  When the file has `:snapshot_every` records or `:max_bytes` bytes it is compacted: a new file
  holding one snapshot and the end mark is written and synced beside it, then renamed over it.

  ## Durable or refused

  A record is appended with its end mark after it, then synced; only then does `record/2` say
  `:ok`. When a write or sync fails (a full disk):

    * the caller gets `{:error, reason}`: SUN_COMM does not acknowledge the string (`E`); a
      command whose dispatch, status or end could not be recorded ends `ERROR JOURNAL WRITE
      FAILED` (`Vws.CEC.Mailbox`), never DONE;
    * the file is cut back to its last whole record and its end mark written again, so no torn
      record stays in front of later ones;
    * the journal is *not healthy*: every record is refused at once (`health/1` says why; the log
      says which string was refused) — the node accepts no work — until a fresh snapshot file has
      been written, tried every `:retry_ms` (2 s); then it logs that it is healthy again.

  A program (the NC file, NC_UP) that cannot be stored makes it not healthy too.

  ## Programs

  The NC file and NC_UP are not log records (a program may be megabytes): each is a file of its
  own in the journal's directory (`nc_file`, `nc_up`), written whole to a temporary file, synced,
  and renamed over the old one (`store_lines/3`), so after a crash it is the old program or the
  new one, never a part. It is written before the mailbox shows it, as every status is.

  A program DOWNLOAD_HP brought into the workstation's program library (`Vws.CEC.Library`,
  durable before the NC file is written) is not written twice: the NC file's file holds
  `{:library, name, version, digest}`, and a restart reads that version back (whole, with that
  SHA-256 digest). A version is never removed from the library; one that cannot be read (the
  workstation started on another library directory) restores no NC file and says so in the
  log, as a damaged file does.

  ## Restart

  When the journal opens on a fresh mailbox table it replays the log: command statuses, CMD_IN,
  the last sequence number and the work-volume leases come back as they were. A command that was
  `EXECUTING` — or acknowledged but not yet dispatched — when the workstation went down answers
  `ERROR INTERRUPTED BY RESTART` and is never run again by itself: a robot move is physical; its
  partition's safe clean-up (`Vws.CEC.Journal.interrupted/1`, e.g. the vise's valves off) is what runs
  instead, when the partition starts. The
  leases are kept because what they stand for outlived the workstation: the arm that was moving
  into the vise is in the table's volume still, and no cycle may start until it has left.

  **Replay is total and damage is loud.** Nothing in the file stops the start. Bytes that are no
  frame (a bit flip, zeroed or random blocks, a file cut short or empty, a missing end mark) and
  records this version cannot apply (a newer version's, a shape it does not know) are each logged
  with their offset; the file is copied aside as `journal.damaged-<UTC time>` in the same
  directory; and everything the lost bytes could have changed reads `NO DATA (JOURNAL DAMAGED)`
  or `NO DATA (JOURNAL RECORD UNREADABLE)` (`Vws.CEC.Journal.Replay`) — never an older status as
  the current one. The next command of a partition makes its status known again.

  A lease taken or given back in the lost part is not known either, so after damage every work
  volume is held by `:journal` (reason `:damaged`), which shares with nobody: the robot, the
  machine, the vise and the material handling are all refused (`ERROR INTERLOCK TABLE HELD BY
  JOURNAL`) until someone who has looked at the cell gives the volume back with
  `Vws.CEC.Interlock.release(ws, volume, :journal)` (the log line says so, and the release is
  journaled like any other).

  The file is compacted to one snapshot of the restored state as it opens, so damage never
  stands in front of new records (and statuses marked unknown stay so across restarts until a
  command changes them).

  A journal of the `disk_log` format of earlier versions (`journal.1`, … without `journal.log`)
  is read once, as well as it can be: its records carry no checksums, so whatever it could not
  read marks the statuses unknown as above; it is then moved aside (`journal.disk_log-<time>`).

  One OS process at a time may write a journal directory: a `LOCK` file names it, and a
  workstation whose directory is held by another live OS process does not start (one left by a
  process that is gone, after a `kill -9`, is taken over). A directory that cannot be made or
  written stops the start with the reason in words.

  ## Options

    * `:workstation` (required), `:dir` — the directory of the journal (required)
    * `:max_bytes` (1 MiB), `:snapshot_every` (500 records), `:retry_ms` (2,000)
  """
  use GenServer
  require Logger

  alias Vws.CEC.{Interlock, Mailbox}
  alias Vws.CEC.Journal.{Log, Replay}

  # the mailbox's recorder: every change is given here before it is visible
  @behaviour Vws.CEC.Mailbox.Recorder

  @interrupted {:error, "INTERRUPTED BY RESTART"}
  @journal_failed {:error, "JOURNAL WRITE FAILED"}
  @file_name "journal.log"

  @doc false
  def child_spec(opts), do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}}

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    GenServer.start_link(__MODULE__, opts, name: Vws.Names.via(ws, :journal))
  end

  @doc """
  Appends `record` to the workstation's journal and syncs it to disk. Does nothing when the
  workstation has no journal. Returns `{:error, reason}` when the record could not be made
  durable: the write failed, or the journal is not healthy (`{:error, :not_healthy}`).

  A journal whose process has ended records nothing (`{:error, :journal_down}`): the workstation
  is going down, and what its parts still do on the way — a command ended `ERROR VAL II LINK
  DOWN` because the VAL II's link is being stopped with them — is not what the equipment did.
  The command stays in flight in the journal and answers `ERROR INTERRUPTED BY RESTART`.
  """
  @impl Vws.CEC.Mailbox.Recorder
  @spec record(:ets.tid(), tuple) :: :ok | {:error, term}
  def record(table, record) do
    case :ets.lookup(table, :journal) do
      [] -> :ok
      [{:journal, journal}] -> call(journal, {:record, record})
    end
  end

  # The journal is linked to the workstation's supervisor and does not trap exits: it is gone
  # before anything its supervisor's death sets off further down reaches this point.
  defp call(journal, request) do
    GenServer.call(journal, request, :infinity)
  catch
    :exit, _ -> {:error, :journal_down}
  end

  @doc """
  Whether the workstation's journal accepts records: `:ok`, `{:error, words}` (not healthy, and
  why), or `:none` (no journal, or it is not running).
  """
  @spec health(term) :: :ok | {:error, String.t()} | :none
  def health(ws) do
    case Vws.Names.whereis(ws, :journal) do
      nil -> :none
      pid -> with {:error, :journal_down} <- call(pid, :health), do: :none
    end
  end

  @doc "Every record in the journal's file, oldest first (for inspection and tests)."
  @spec records(term) :: [tuple]
  def records(ws) do
    dir = GenServer.call(Vws.Names.via(ws, :journal), :dir)

    for {:record, _off, payload} <- Log.parse(File.read!(Path.join(dir, @file_name))),
        do: :erlang.binary_to_term(payload)
  end

  @doc """
  The command of `partition` the restart interrupted, `{number, text}` (text nil when the journal
  has only its number), or `{nil, :unknown}` when its status was lost with a damaged journal (a
  command may have been under way), taken once: the restarted partition's safe clean-up runs
  for it.
  """
  @spec take_interrupted(term, atom) ::
          {0..9999, String.t() | nil} | {nil, :unknown} | nil
  def take_interrupted(ws, partition) do
    case :ets.take(Mailbox.table(ws), {:interrupted, partition}) do
      [{_, number, text}] -> {number, text}
      [] -> nil
    end
  end

  @doc """
  Stores a program (`:nc_file` or `:nc_up`) in the journal's directory, whole or not at all, and
  syncs it to disk: its lines, or the reference `{:library, name, version, digest}` to the
  program library's version that holds them (see "Programs"). Does nothing when the workstation
  has no journal. A program that cannot be stored makes the journal not healthy (a full disk),
  as a record does.
  """
  @impl Vws.CEC.Mailbox.Recorder
  @spec store_lines(:ets.tid(), :nc_file | :nc_up, Vws.CEC.Mailbox.Recorder.program()) ::
          :ok | {:error, term}
  def store_lines(table, key, program) when key in [:nc_file, :nc_up] do
    case :ets.lookup(table, :journal) do
      [] -> :ok
      [{:journal, journal}] -> call(journal, {:store_lines, key, program})
    end
  end

  defp write_whole(path, program) do
    tmp = path <> ".new"

    bin =
      case program do
        lines when is_list(lines) -> :erlang.term_to_binary({:lines, lines})
        {:library, _name, _version, _digest} = ref -> :erlang.term_to_binary(ref)
      end

    with {:ok, fd} <- :file.open(tmp, [:write, :raw, :binary]),
         :ok <- write_sync_close(fd, bin) do
      :file.rename(tmp, path)
    else
      error ->
        _ = :file.delete(tmp)
        error
    end
  end

  defp write_sync_close(fd, bin) do
    result = with :ok <- :file.write(fd, bin), do: :file.sync(fd)
    :file.close(fd)
    result
  end

  defp read_lines(ws, dir, key) do
    path = Path.join(dir, Atom.to_string(key))

    with {:ok, bin} <- File.read(path),
         {:lines, lines} when is_list(lines) <- safe_term(bin),
         true <- Enum.all?(lines, &is_binary/1) do
      lines
    else
      {:error, :enoent} ->
        []

      {:library, name, version, digest} ->
        from_library(ws, path, key, name, version, digest)

      _other ->
        Logger.error("#{path} unreadable (damaged): no #{key} restored")
        []
    end
  end

  # The program a reference names, read back from the library: the version must read whole and
  # be the very bytes recorded (its digest), else nothing is restored, loudly.
  defp from_library(ws, path, key, name, version, digest) do
    # (a version deleted from the library since still holds the NC file's bytes)
    case Vws.CEC.Library.read(ws, name, version, deleted: true) do
      {:ok, bytes, %{digest: ^digest}} ->
        Vws.Links.DNC.Program.from_text(bytes)

      other ->
        why =
          case other do
            {:ok, _bytes, _other_version} -> "other bytes"
            {:error, reason} -> Vws.Codecs.WC.Words.of(reason)
          end

        Logger.error(
          "#{path} names #{name} version #{version} of the program library, which cannot be " <>
            "read (#{why}): no #{key} restored"
        )

        []
    end
  end

  defp safe_term(bin) do
    :erlang.binary_to_term(bin, [:safe])
  rescue
    ArgumentError -> :damaged
  end

  ## Server

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    dir = Keyword.fetch!(opts, :dir)

    case File.mkdir_p(dir) do
      :ok -> :ok
      {:error, why} -> raise "journal directory #{dir} cannot be made: #{words(why)}"
    end

    :ok = lock!(dir)
    table = Mailbox.table(ws)

    s = %{
      workstation: ws,
      dir: dir,
      path: Path.join(dir, @file_name),
      fd: nil,
      pos: 0,
      records: 0,
      state: nil,
      healthy: :ok,
      max_bytes: Keyword.get(opts, :max_bytes, 1024 * 1024),
      every: Keyword.get(opts, :snapshot_every, 500),
      retry_ms: Keyword.get(opts, :retry_ms, 2_000)
    }

    # Restore only into a fresh table: if only the journal restarted, the mailboxes are current.
    if :ets.insert_new(table, {:journal_restored, true}) do
      restore(ws, table, dir, s.path)
      for key <- [:nc_file, :nc_up], do: :ets.insert(table, {key, read_lines(ws, dir, key)})
    end

    # Compact: the snapshot of the restored state replaces everything before it, so a damaged
    # record never stands in front of the records written from now on.
    s = %{s | state: state_of(table)}

    s =
      case compact(s) do
        {:ok, s} ->
          s

        {:error, why} ->
          Logger.error(
            "journal of #{inspect(ws)} cannot be written (#{words(why)}): " <>
              "the workstation accepts no work until it can"
          )

          not_healthy(s, why)
      end

    :ets.insert(table, {:journal, self()})
    :ok = Mailbox.attach_recorder(table, __MODULE__)
    {:ok, s}
  end

  @impl true
  def handle_call({:record, record}, _from, %{healthy: {:error, since, why}} = s) do
    Logger.error(
      "journal of #{inspect(s.workstation)} not healthy since #{since} (#{why}): " <>
        "#{what(record)} refused " <>
        "(ERROR JOURNAL WRITE FAILED); a fresh snapshot is tried every #{s.retry_ms} ms"
    )

    {:reply, {:error, :not_healthy}, s}
  end

  def handle_call({:record, record}, _from, s) do
    with {:ok, s} <- maybe_compact(s),
         {:ok, s} <- append(s, record) do
      {:reply, :ok, %{s | state: applied(Replay.apply_record(record, s.state), s.state)}}
    else
      {:error, why, s} ->
        Logger.error(
          "journal of #{inspect(s.workstation)}: write failed (#{words(why)}): " <>
            "#{what(record)} not recorded " <>
            "(ERROR JOURNAL WRITE FAILED); the workstation accepts no work until a fresh " <>
            "snapshot is written"
        )

        {:reply, {:error, why}, not_healthy(%{s | state: failed(record, s.state)}, why)}
    end
  end

  def handle_call({:store_lines, key, _lines}, _from, %{healthy: {:error, since, why}} = s) do
    Logger.error(
      "journal of #{inspect(s.workstation)} not healthy since #{since} (#{why}): " <>
        "#{key} not stored, the old one kept"
    )

    {:reply, {:error, :not_healthy}, s}
  end

  def handle_call({:store_lines, key, program}, _from, s) do
    case write_whole(Path.join(s.dir, Atom.to_string(key)), program) do
      :ok ->
        {:reply, :ok, s}

      {:error, why} ->
        Logger.error(
          "journal of #{inspect(s.workstation)}: #{key} not stored (#{words(why)}): " <>
            "the old program is kept"
        )

        {:reply, {:error, why}, not_healthy(s, why)}
    end
  end

  def handle_call(:health, _from, %{healthy: :ok} = s), do: {:reply, :ok, s}

  def handle_call(:health, _from, %{healthy: {:error, since, why}} = s),
    do: {:reply, {:error, "JOURNAL WRITE FAILED AT #{since} (#{String.upcase(why)})"}, s}

  def handle_call(:dir, _from, s), do: {:reply, s.dir, s}

  @impl true
  def handle_info(:retry, %{healthy: :ok} = s), do: {:noreply, s}

  def handle_info(:retry, s) do
    case compact(s) do
      {:ok, s} ->
        Logger.warning(
          "journal of #{inspect(s.workstation)} healthy again: a fresh snapshot is written, " <>
            "strings are accepted"
        )

        {:noreply, %{s | healthy: :ok}}

      {:error, _why} ->
        Process.send_after(self(), :retry, s.retry_ms)
        {:noreply, s}
    end
  end

  def handle_info(_other, s), do: {:noreply, s}

  # the change an unrecorded record stands for: what the mailbox shows instead
  # (`Vws.CEC.Mailbox`: ERROR JOURNAL WRITE FAILED), written with the next snapshot. A string
  # not recorded was not acknowledged, a lease not recorded was not granted (or, released,
  # stays held on disk: the safe side).
  defp failed({:status, p, n, _status, text}, state),
    do: applied_or(Replay.apply_record({:status, p, n, @journal_failed, text}, state), state)

  defp failed({tag, p, n, _status}, state) when tag in [:status, :finish],
    do: applied_or(Replay.apply_record({tag, p, n, @journal_failed}, state), state)

  defp failed({:unknown_status, l, n, _status}, state),
    do: applied_or(Replay.apply_record({:unknown_status, l, n, @journal_failed}, state), state)

  defp failed(_record, state), do: state

  defp applied_or({:ok, state}, _old), do: state
  defp applied_or(_error, old), do: old

  # a record the live system writes and this version cannot apply is a bug: it is logged, and
  # what it could have changed is marked as a replay would
  defp applied({:ok, state}, _old), do: state
  defp applied({:partly, state, why, scope}, _old), do: marked(state, why, scope)
  defp applied({:error, why, scope}, old), do: marked(old, why, scope)

  defp marked(state, why, scope) do
    Logger.error("journal record not applicable (#{why}): marked unknown")
    Replay.mark(state, scope, Replay.unreadable())
  end

  defp not_healthy(%{healthy: {:error, _, _}} = s, _why), do: s

  defp not_healthy(s, why) do
    Process.send_after(self(), :retry, s.retry_ms)
    since = Calendar.strftime(DateTime.utc_now(), "%H:%M:%S UTC")
    %{s | healthy: {:error, since, words(why)}}
  end

  defp what({:string, seq, _line, _}), do: "string #{Vws.Codecs.WC.Command.pad4(seq)}"
  defp what(record) when is_tuple(record), do: "record #{elem(record, 0)}"

  defp words(why) when is_atom(why) do
    case :file.format_error(why) do
      ~c"unknown POSIX error" ++ _ -> why |> Atom.to_string() |> String.replace("_", " ")
      text -> List.to_string(text)
    end
  end

  defp words(why) when is_binary(why), do: why
  defp words(why), do: inspect(why)

  ## The file

  defp maybe_compact(%{records: n, every: every, pos: pos, max_bytes: max} = s)
       when n >= every or pos >= max do
    case compact(s) do
      {:ok, s} -> {:ok, s}
      {:error, why} -> {:error, why, s}
    end
  end

  defp maybe_compact(s), do: {:ok, s}

  # A new file holding one snapshot of the state and the end mark, synced, then renamed over the
  # old one: after a crash it is the old file or the new one, each whole.
  defp compact(s) do
    tmp = s.path <> ".new"
    snapshot = Log.record({:snapshot, s.state})
    _ = :file.delete(tmp)

    with {:ok, fd} <- :file.open(tmp, [:read, :write, :raw, :binary]),
         :ok <- write_or_close(fd, [snapshot, Log.end_mark()]),
         :ok <- sync_or_close(fd),
         :ok <- rename_or_close(fd, tmp, s.path) do
      if s.fd, do: :file.close(s.fd)
      {:ok, %{s | fd: fd, pos: byte_size(snapshot), records: 0}}
    else
      {:error, why} ->
        _ = :file.delete(tmp)
        {:error, why}
    end
  end

  defp write_or_close(fd, data), do: close_on_error(fd, :file.write(fd, data))
  defp sync_or_close(fd), do: close_on_error(fd, :file.sync(fd))
  defp rename_or_close(fd, from, to), do: close_on_error(fd, :file.rename(from, to))

  defp close_on_error(_fd, :ok), do: :ok

  defp close_on_error(fd, error) do
    :file.close(fd)
    error
  end

  defp append(%{fd: nil} = s, _record), do: {:error, :not_open, s}

  defp append(s, record) do
    frame = Log.record(record)

    with :ok <- :file.pwrite(s.fd, s.pos, [frame, Log.end_mark()]),
         :ok <- :file.datasync(s.fd) do
      {:ok, %{s | pos: s.pos + byte_size(frame), records: s.records + 1}}
    else
      {:error, why} -> {:error, why, cut_back(s)}
    end
  end

  # After a failed write: the file back to its last whole record and its end mark, so nothing
  # torn stays in the middle of the log. If even that fails, the next start finds the file
  # damaged and says so; the fresh snapshot (retried) replaces it.
  defp cut_back(s) do
    result =
      with {:ok, _} <- :file.position(s.fd, s.pos),
           :ok <- :file.truncate(s.fd),
           :ok <- :file.pwrite(s.fd, s.pos, Log.end_mark()),
           do: :file.datasync(s.fd)

    if result != :ok,
      do: Logger.error("journal could not be cut back to its last record: #{inspect(result)}")

    s
  end

  # One OS process at a time writes a journal directory: two would damage each other's records.
  # The lock names the OS process holding it; one left by a process that is gone (kill -9) is
  # taken over, and this VM may take its own again (a workstation restarted in the same node).
  defp lock!(dir) do
    path = Path.join(dir, "LOCK")
    me = System.pid()

    case File.read(path) do
      {:ok, holder} ->
        holder = String.trim(holder)

        if holder != me and os_process_alive?(holder) do
          raise "journal directory #{dir} is in use by OS process #{holder}"
        end

      {:error, _} ->
        :ok
    end

    case File.write(path, me) do
      :ok -> :ok
      {:error, why} -> raise "journal directory #{dir} cannot be written: #{words(why)}"
    end
  end

  defp os_process_alive?(pid) do
    case Integer.parse(pid) do
      {_n, ""} ->
        match?({_, 0}, System.cmd("kill", ["-0", pid], stderr_to_stdout: true))

      _ ->
        false
    end
  end

  @impl true
  def terminate(_reason, s) do
    if s.fd, do: :file.close(s.fd)
    # a stop that runs this lets the directory go; a kill leaves the lock to be taken over
    if File.read(Path.join(s.dir, "LOCK")) == {:ok, System.pid()},
      do: File.rm(Path.join(s.dir, "LOCK"))

    :ok
  end

  ## Restoring

  # The restorable state: the mailboxes' (per partition {number, status, cmd_in}, the last
  # string, unknown set letters) and the interlock's leases, the earliest first.
  defp state_of(table), do: Map.put(Mailbox.dump(table), :leases, Interlock.leases(table))

  defp restore(ws, table, dir, path) do
    case read_journal(dir, path) do
      :none ->
        :ok

      {:ok, items, source} ->
        {state, problems} = Replay.replay(items, state_of(table))

        state =
          if problems != [] do
            state = hold_unknown_volumes(state)
            report_damage(ws, source, problems, state)
            state
          else
            state
          end

        load(table, state)
    end
  end

  # {:ok, items, file} or :none (a journal never written: a fresh start)
  defp read_journal(dir, path) do
    case File.read(path) do
      {:ok, bin} ->
        {:ok, Log.parse(bin), path}

      {:error, :enoent} ->
        case Vws.CEC.Journal.DiskLog.read(dir) do
          :none -> :none
          {:ok, items, aside} -> {:ok, items, aside}
        end

      {:error, why} ->
        # there is a journal, and it cannot be read: everything it held is unknown
        {:ok, [{:damaged, 0, {:unreadable_file, words(why)}}], path}
    end
  end

  # A lease taken or given back in the damaged part is not known: where the arm was, whether
  # the tray was locked. An interlock that cannot be decided denies, so every work volume is held
  # by `:journal` (reason `:damaged`), which shares with nobody, until a person who has looked at
  # the cell gives it back: `Vws.CEC.Interlock.release(ws, volume, :journal)` in iex (journaled
  # like any release). The leases read before the damage are kept as well.
  @volumes [:table, :tray1, :tray2]

  defp hold_unknown_volumes(state) do
    volumes = Enum.uniq(@volumes ++ for({v, _h, _r} <- state.leases, do: v))
    held = for v <- volumes, not Enum.any?(state.leases, &match?({^v, :journal, _}, &1)), do: v
    %{state | leases: state.leases ++ for(v <- held, do: {v, :journal, [:damaged]})}
  end

  defp report_damage(ws, source, problems, state) do
    aside = copy_aside(source)

    for {off, why} <- problems do
      Logger.error("journal of #{inspect(ws)} damaged at byte #{off} of #{source}: #{why}")
    end

    unknown =
      for {p, %{status: {:no_data, why}}} <- state.partitions,
          do: "#{p |> Atom.to_string() |> String.upcase()}_CMD NO DATA (#{why})"

    Logger.error(
      "journal of #{inspect(ws)}: #{length(problems)} damaged or unreadable place(s); " <>
        "a copy is kept as #{aside}; restored as unknown: " <>
        if(unknown == [], do: "no command status", else: Enum.join(unknown, ", ")) <>
        "; leases read before the damage kept, and every work volume held by JOURNAL until " <>
        "someone who has looked at the cell releases it " <>
        "(Vws.CEC.Interlock.release(#{inspect(ws)}, :table, :journal), likewise :tray1, :tray2)"
    )
  end

  defp copy_aside(source) do
    stamp = Calendar.strftime(DateTime.utc_now(), "%Y%m%dT%H%M%S%fZ")
    aside = Path.join(Path.dirname(source), "journal.damaged-" <> stamp)

    case File.cp_r(source, aside) do
      {:ok, _} -> aside
      {:error, why, _} -> "none (#{words(why)})"
    end
  end

  defp load(table, state) do
    partitions =
      Map.new(state.partitions, fn
        {p, %{status: :executing} = c} -> {p, %{c | status: @interrupted}}
        other -> other
      end)

    :ok = Mailbox.load(table, %{state | partitions: partitions})
    :ok = Interlock.restore(table, state.leases)

    interrupted = for {p, %{status: :executing, number: n}} <- state.partitions, do: {p, n}

    # what each restarted partition's safe clean-up is for (Vws.CEC.Partition, interrupted/2)
    for {p, %{status: :executing, number: n, cmd_in: {in_n, text}}} <- state.partitions do
      :ets.insert(table, {{:interrupted, p}, n, if(in_n == n, do: text)})
    end

    # a status lost with damaged bytes may have been a command under way: its clean-up runs too
    for {p, %{status: {:no_data, _}}} <- state.partitions do
      :ets.insert(table, {{:interrupted, p}, nil, :unknown})
    end

    if interrupted != [] do
      Logger.warning(
        "restored from the journal; interrupted by the restart: #{inspect(interrupted)}"
      )
    end

    if state.leases != [] do
      Logger.warning(
        "restored from the journal; leases still held: " <>
          Enum.map_join(state.leases, ", ", fn {v, h, r} -> "#{v} #{h} #{inspect(r)}" end)
      )
    end

    :ok
  end
end
