defmodule Vws.CEC.Journal do
  @moduledoc """
  The workstation's durable command journal, on OTP's `disk_log`.

  Every accepted command string and every command-status change is written and synced to disk
  before SUN_COMM acknowledges the string or the mailbox shows the status, so a WC that asks the
  status of any command it sent gets the true answer even after the workstation — or the whole
  node — restarted.

  ## Records

    * `{:string, seq, line, [{partition, number}]}` — a command string SUN_COMM accepted (before `05A`)
    * `{:status, partition, number, status}` — a command status written outright (dispatch, a rule)
    * `{:finish, partition, number, status}` — a command ended: applied only while the status
      location still shows `number`, exactly as `Vws.CEC.Mailbox.finish/4` does
    * `{:unknown_status, letter, number, status}` — a command of a set letter the CEC does not
      know, refused by rule 5 (`Vws.CEC.Mailbox.put_unknown_status/4`)
    * `{:lease, volume, holder, reasons}` — a work-volume lease (`Vws.CEC.Interlock`) taken or
      changed, `reasons` `[]` when it ended: written before the lease counts
    * `{:snapshot, state}` — the whole restorable state, written when the journal opens and every
      `:snapshot_every` records, so the newest state survives the wrap of old files

  ## Programs

  The NC file and NC_UP are not log records (a program may be megabytes): each is a file of its
  own in the journal's directory (`nc_file`, `nc_up`), written whole to a temporary file, synced,
  and renamed over the old one (`store_lines/3`), so after a crash it is the old program or the
  new one, never a part. It is written before the mailbox shows it, as every status is.

  ## Restart

  When the journal opens on a fresh mailbox table it replays the log: command statuses, CMD_IN,
  the last sequence number and the work-volume leases come back as they were. A command that was
  `EXECUTING` — or acknowledged but not yet dispatched — when the workstation went down answers
  `ERROR INTERRUPTED BY RESTART` and is never run again by itself: a robot move is physical; its
  partition's safe clean-up (`Vws.CEC.Journal.interrupted/1`, e.g. the vise's valves off) is what runs
  instead, when the partition starts. The
  leases are kept because what they stand for outlived the workstation: the arm that was moving
  into the vise is in the table's volume still, and no cycle may start until it has left.

  One OS process at a time may write a journal directory: a `LOCK` file names it, and a
  workstation whose directory is held by another live OS process does not start (one left by a
  process that is gone, after a `kill -9`, is taken over).

  The log is a wrap log (`:max_bytes` × `:max_files`, bounded) opened with `repair: true`; it is
  read record by record, so a torn last record (power lost in the middle of a write) is cut off and
  the records before it are kept. Each time the journal opens it is compacted to one snapshot of
  the restored state, so damage never stands in front of new records.

  ## Options

    * `:workstation` (required), `:dir` — the directory of the log files (required)
    * `:max_bytes` (256 KiB per file), `:max_files` (8), `:snapshot_every` (500 records)
  """
  use GenServer
  require Logger

  alias Vws.CEC.{Interlock, Mailbox}

  # the mailbox's recorder: every change is given here before it is visible
  @behaviour Vws.CEC.Mailbox

  @interrupted {:error, "INTERRUPTED BY RESTART"}

  @doc false
  def child_spec(opts), do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}}

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    GenServer.start_link(__MODULE__, opts, name: Vws.Names.via(ws, :journal))
  end

  @doc """
  Appends `record` to the workstation's journal and syncs it to disk. Does nothing when the
  workstation has no journal. Returns `{:error, reason}` when the record could not be made durable.

  A journal whose process has ended records nothing (`{:error, :journal_down}`): the workstation
  is going down, and what its parts still do on the way — a command ended `ERROR VAL II LINK
  DOWN` because the VAL II's link is being stopped with them — is not what the equipment did.
  The command stays in flight in the journal and answers `ERROR INTERRUPTED BY RESTART`.
  """
  @impl Vws.CEC.Mailbox
  @spec record(:ets.tid(), tuple) :: :ok | {:error, term}
  def record(table, record) do
    case :ets.lookup(table, :journal) do
      [] ->
        :ok

      [{:journal, log, every, journal}] ->
        # The journal is linked to the workstation's supervisor and does not trap exits: it is
        # gone before anything its supervisor's death sets off further down reaches this point.
        if Process.alive?(journal) do
          # A snapshot goes before the record: the table does not show the record's change yet.
          if :ets.update_counter(table, :journal_records, 1, {:journal_records, 0}) >= every do
            :ets.insert(table, {:journal_records, 0})
            :disk_log.log(log, {:snapshot, state_of(table)})
          end

          with :ok <- :disk_log.log(log, record), do: :disk_log.sync(log)
        else
          {:error, :journal_down}
        end
    end
  end

  @doc "Every record in the journal, oldest first (for inspection and tests)."
  @spec records(term) :: [tuple]
  def records(ws) do
    [{:journal, log, _, _}] = :ets.lookup(Mailbox.table(ws), :journal)
    read_all(log)
  end

  @doc """
  The command of `partition` the restart interrupted, `{number, text}` (text nil when the journal
  has only its number), taken once: the restarted partition's safe clean-up runs for it.
  """
  @spec take_interrupted(term, atom) :: {0..9999, String.t() | nil} | nil
  def take_interrupted(ws, partition) do
    case :ets.take(Mailbox.table(ws), {:interrupted, partition}) do
      [{_, number, text}] -> {number, text}
      [] -> nil
    end
  end

  @doc """
  Stores a program (`:nc_file` or `:nc_up`) in the journal's directory, whole or not at all, and
  syncs it to disk. Does nothing when the workstation has no journal.
  """
  @impl Vws.CEC.Mailbox
  @spec store_lines(:ets.tid(), :nc_file | :nc_up, [binary]) :: :ok | {:error, term}
  def store_lines(table, key, lines) when key in [:nc_file, :nc_up] do
    case :ets.lookup(table, :journal_dir) do
      [] -> :ok
      [{:journal_dir, dir}] -> write_whole(Path.join(dir, Atom.to_string(key)), lines)
    end
  end

  defp write_whole(path, lines) do
    tmp = path <> ".new"
    bin = :erlang.term_to_binary({:lines, lines})

    with {:ok, fd} <- :file.open(tmp, [:write, :raw, :binary]),
         :ok <- write_sync_close(fd, bin) do
      :file.rename(tmp, path)
    end
  end

  defp write_sync_close(fd, bin) do
    result = with :ok <- :file.write(fd, bin), do: :file.sync(fd)
    :file.close(fd)
    result
  end

  defp read_lines(dir, key) do
    path = Path.join(dir, Atom.to_string(key))

    with {:ok, bin} <- File.read(path),
         {:lines, lines} when is_list(lines) <- safe_term(bin) do
      lines
    else
      {:error, :enoent} ->
        []

      other ->
        Logger.error("#{path} unreadable (#{inspect(other, limit: 5)}): no #{key} restored")
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
    File.mkdir_p!(dir)
    :ok = lock!(dir)
    log = {:vws_journal, ws}
    size = {Keyword.get(opts, :max_bytes, 256 * 1024), Keyword.get(opts, :max_files, 8)}

    case :disk_log.open(
           name: log,
           file: String.to_charlist(Path.join(dir, "journal")),
           type: :wrap,
           size: size,
           repair: true
         ) do
      {:ok, ^log} ->
        :ok

      {:repaired, ^log, {:recovered, n}, {:badbytes, bad}} ->
        Logger.warning(
          "journal of #{inspect(ws)} repaired: #{n} records kept, #{bad} torn bytes dropped"
        )
    end

    table = Mailbox.table(ws)

    # Restore only into a fresh table: if only the journal restarted, the mailboxes are current.
    if :ets.insert_new(table, {:journal_restored, true}) do
      restore(table, read_all(log))
      for key <- [:nc_file, :nc_up], do: :ets.insert(table, {key, read_lines(dir, key)})
    end

    :ets.insert(table, {:journal_dir, dir})

    # Compact: the snapshot of the restored state replaces everything before it, so a damaged
    # record never stands in front of the records written from now on.
    :ok = :disk_log.truncate(log)
    :ok = :disk_log.log(log, {:snapshot, state_of(table)})
    :ok = :disk_log.sync(log)
    :ets.insert(table, {:journal, log, Keyword.get(opts, :snapshot_every, 500), self()})
    :ok = Mailbox.attach_recorder(table, __MODULE__)
    {:ok, %{workstation: ws, log: log, dir: dir}}
  end

  @impl true
  def terminate(_reason, s) do
    :disk_log.close(s.log)
    # a stop that runs this lets the directory go; a kill leaves the lock to be taken over
    if File.read(Path.join(s.dir, "LOCK")) == {:ok, System.pid()},
      do: File.rm(Path.join(s.dir, "LOCK"))

    :ok
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

    File.write!(path, me)
  end

  defp os_process_alive?(pid) do
    case Integer.parse(pid) do
      {_n, ""} ->
        match?({_, 0}, System.cmd("kill", ["-0", pid], stderr_to_stdout: true))

      _ ->
        false
    end
  end

  defp read_all(log), do: read_all(log, :start, [])

  # One term at a time: a damaged record loses only itself and what follows it, never the good
  # records read in the same block.
  defp read_all(log, cont, acc) do
    case :disk_log.chunk(log, cont, 1) do
      :eof ->
        acc |> Enum.reverse() |> List.flatten()

      {:error, reason} ->
        # Better a workstation that starts with what could be read than one that cannot start.
        Logger.error(
          "journal partly unreadable (#{inspect(reason)}): restoring from the records before it"
        )

        acc |> Enum.reverse() |> List.flatten()

      {cont, terms} ->
        read_all(log, cont, [terms | acc])

      {cont, terms, _badbytes} ->
        read_all(log, cont, [terms | acc])
    end
  end

  ## Restoring

  # The restorable state: the mailboxes' (per partition {number, status, cmd_in}, the last
  # string, unknown set letters) and the interlock's leases, the earliest first.
  defp state_of(table), do: Map.put(Mailbox.dump(table), :leases, Interlock.leases(table))

  defp restore(_table, []), do: :ok

  defp restore(table, records) do
    state = Enum.reduce(records, state_of(table), &apply_record/2)

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

  # a snapshot written before leases were journaled has none
  defp apply_record({:snapshot, snapshot}, _state),
    do: snapshot |> Map.put_new(:leases, []) |> Map.put_new(:unknown, %{})

  defp apply_record({:unknown_status, letter, n, status}, state),
    do: put_in(state.unknown[letter], {n, status})

  # a lease keeps its place among the others (the earliest first) while it is held
  defp apply_record({:lease, volume, holder, reasons}, state) do
    held? = &match?({^volume, ^holder, _}, &1)

    leases =
      cond do
        reasons == [] ->
          Enum.reject(state.leases, held?)

        Enum.any?(state.leases, held?) ->
          Enum.map(state.leases, &if(held?.(&1), do: {volume, holder, reasons}, else: &1))

        true ->
          state.leases ++ [{volume, holder, reasons}]
      end

    %{state | leases: leases}
  end

  defp apply_record({:string, seq, line, commands}, state) do
    # acknowledged: until a later record says otherwise, each command counts as under way
    state = %{state | last_string: {seq, line}}

    Enum.reduce(commands, state, fn {p, n}, st ->
      update_in(st.partitions[p], &%{&1 | number: n, status: :executing})
    end)
  end

  defp apply_record({:status, p, n, status, text}, state) do
    update_in(state.partitions[p], &%{&1 | number: n, status: status, cmd_in: {n, text}})
  end

  defp apply_record({:status, p, n, status}, state) do
    update_in(state.partitions[p], &%{&1 | number: n, status: status})
  end

  defp apply_record({:finish, p, n, status}, state) do
    update_in(state.partitions[p], fn
      %{number: ^n} = entry -> %{entry | status: status}
      entry -> entry
    end)
  end

  defp apply_record(_unknown, state), do: state
end
