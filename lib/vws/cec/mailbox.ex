defmodule Vws.CEC.Mailbox do
  @moduledoc """
  The CEC's mailboxes (seed §2.3.5–2.3.6): memory files shared by the partitions, here one ETS table
  per workstation owned by `Vws.CEC.Mailbox.Owner`.

  ## Layout

    * **Device-status locations 1–14**, written by VWS_STATUS (and by ROBOT and MONARCH for what only
      they can read) and answered by SUN_COMM's Status subroutine:

      | loc | name          | loc | name          |
      |-----|---------------|-----|---------------|
      | 1   | `GRIPPER`     | 8   | `MONARCH`     |
      | 2   | `TABLE`       | 9   | `WHERE_ROBOT` |
      | 3   | `VISE`        | 10  | `PALLET`      |
      | 4   | `TRAYS`       | 11  | `SENSORS` (the 16-element array B) |
      | 5   | `VACUUM`      | 12–14 | spare       |
      | 6   | `TLI_TABLE`   |     |               |
      | 7   | `CHANGER_1`   |     |               |

      Each holds a value (usually the status text) and the monotonic time it was written, so
      a reader can tell a fresh reading from a stale one.

    * **Command-status locations 34–39**, one per command partition: ROBOT 34, MONARCH 35,
      GRIPPER 36, FIXTURE 37, VACUUM 38, HYDRAULIC 39. Each holds the number of the last command of
      that set and its status: `:none`, `:executing`, `:done` or `{:error, reason}` — or
      `{:no_data, why}` when a damaged journal could not restore it.

    * **CMD_IN**: the latest command text and number per set; **in flight**: the number of the
      command a partition has been given and not yet finished (at most one per set).

    * **NC file** (the program downloaded from the WC, DOWNLOAD_HP) and **NC_UP** (the program
      uploaded from the GE-2000, UPLOAD_GE), as lists of lines.

    * **Interlocks**: the work-volume leases of `Vws.CEC.Interlock` (seed §2.3.8), one entry
      `{:interlock, volume, holder}` per holder.

  ## Durability

  With a journal (`Vws.CEC.Journal`), every command-status change is written to disk before it is
  written here, and a restarted workstation gets its command statuses back. The mailbox does not
  know the journal: a *recorder* — a module implementing `Vws.CEC.Mailbox.Recorder`, attached to
  the table with `attach_recorder/2` — is given every change first (`record/2`, `store_lines/3`
  for the programs); without one, nothing is recorded. The journal reads and restores the mailboxes through
  `dump/1` and `load/2`, never through the table's keys.

  ## Change notices

  Each write that changes a device-status location, a command status or a device's readings is
  announced, after the write, to the processes subscribed to the workstation's event `:mailbox`
  (`Vws.CEC.Events.subscribe(ws, :mailbox)`), as `{:vws_event, ws, :mailbox, {change, system_us}}`
  where `change` is `{:device, loc, value}`, `{:command, partition, number, status, text | nil}`
  (the text when the command is dispatched) or `{:readings, source, value}`; the notices of one
  writer arrive in the order of its writes. The MTConnect agent records every transition so.

  ## LOCK/UNLOCK

  Every write here is one atomic ETS operation (`insert_new` for dispatch, `select_replace` for a
  compare-and-set of a command status), which is what LOCK … OUTPUT … UNLOCK achieved. For a
  longer critical section, `locked/2` runs a function inside the owner process.
  """

  require Logger

  @type workstation :: term
  @type partition :: :robot | :monarch | :gripper | :fixture | :vacuum | :hydraulic
  @typedoc """
  A command status. `{:no_data, why}`: not known — the journal could not restore it
  (`Vws.CEC.Journal`), answered `NO DATA (why)`.
  """
  @type status :: :none | :executing | :done | {:error, String.t()} | {:no_data, String.t()}

  # what a command whose change could not be made durable ends with (`Vws.CEC.Journal`)
  @journal_failed {:error, "JOURNAL WRITE FAILED"}

  @device_locations %{
    1 => "GRIPPER",
    2 => "TABLE",
    3 => "VISE",
    4 => "TRAYS",
    5 => "VACUUM",
    6 => "TLI_TABLE",
    7 => "CHANGER_1",
    8 => "MONARCH",
    9 => "WHERE_ROBOT",
    10 => "PALLET",
    11 => "SENSORS",
    12 => "SPARE",
    13 => "SPARE",
    14 => "SPARE"
  }

  @command_locations [robot: 34, monarch: 35, gripper: 36, fixture: 37, vacuum: 38, hydraulic: 39]
  @partitions Keyword.keys(@command_locations)

  @doc "The command partitions, in mailbox-location order."
  @spec partitions() :: [partition]
  def partitions, do: @partitions

  @doc "The command-status location (34–39) of a partition."
  @spec command_location(partition) :: 34..39
  def command_location(partition), do: Keyword.fetch!(@command_locations, partition)

  @doc "The name of a device-status location (1–14)."
  @spec device_name(1..14) :: String.t()
  def device_name(loc), do: Map.fetch!(@device_locations, loc)

  @doc "The device-status location (1–11) for a status name such as `\"VISE\"`."
  @spec device_location(String.t()) :: 1..11 | nil
  def device_location(name) do
    Enum.find_value(@device_locations, fn {loc, n} -> if n == name and n != "SPARE", do: loc end)
  end

  @doc "The workstation's table. Raises `ArgumentError` if the workstation has no mailboxes."
  @spec table(workstation) :: :ets.tid()
  def table(ws), do: Vws.Names.mailbox_table(ws)

  @doc """
  Keeps the workstation's table in the calling process (`Vws.Names.keep_mailbox_table/1`): the
  processes that write the mailboxes at every poll or string find it without a Registry
  look-up, and a new table (its owner restarted) is looked up again.
  """
  @spec keep_table(workstation) :: :ets.tid()
  def keep_table(ws), do: Vws.Names.keep_mailbox_table(ws)

  @doc "True when the workstation's mailboxes exist."
  @spec exists?(workstation) :: boolean
  def exists?(ws), do: Registry.lookup(Vws.Registry, {ws, :mailbox}) != []

  @doc false
  def initialize(table) do
    now = now()
    for loc <- 1..14, do: :ets.insert(table, {{:device, loc}, nil, now})

    for p <- @partitions do
      :ets.insert(table, {{:command_status, p}, nil, :none})
      :ets.insert(table, {{:cmd_in, p}, nil, nil})
    end

    :ets.insert(table, {:nc_file, []})
    :ets.insert(table, {:nc_up, []})
    :ets.insert(table, {:last_string, nil, nil})
    :ok
  end

  @doc "Runs `fun.(table)` inside the owner, serialised with every other `locked/2` (LOCK/UNLOCK)."
  @spec locked(workstation, (:ets.tid() -> result)) :: result when result: var
  def locked(ws, fun) do
    GenServer.call(Vws.Names.via(ws, :mailbox_owner), {:locked, fun})
  end

  ## Device status (locations 1–14)

  @doc """
  Writes a device-status location with the current monotonic time. A value that differs from the
  one there is announced (see "Change notices").
  """
  @spec put_device(workstation, 1..14, term) :: :ok
  def put_device(ws, loc, value) when loc in 1..14 do
    table = table(ws)
    changed? = :ets.lookup_element(table, {:device, loc}, 2) != value
    :ets.insert(table, {{:device, loc}, value, now()})
    if changed?, do: changed(ws, {:device, loc, value})
    :ok
  end

  @doc """
  Writes a device-status location as `put_device/3` does, unless it was written at or after
  `asked_at` (monotonic ms): `:ok`, or `:newer` (nothing written). For a reader whose answer may
  come back late — a status read asked at `asked_at` — so that what another writer put there
  since (a partition's own confirmation, a drip feed's ACTIVE) is not overwritten with older
  news (`Vws.Partitions.StatusMonitor`). A location not read yet — its `NO DATA (… NOT READ
  YET)` text, written when the workstation starts, perhaps after the read was asked — takes any
  answer. The write happens only if the location is still as it was looked at (one
  `:ets.select_replace/2`): a write in between makes it `:newer`.
  """
  @spec put_device_unless_newer(workstation, 1..14, term, integer) :: :ok | :newer
  def put_device_unless_newer(ws, loc, value, asked_at) when loc in 1..14 do
    table = table(ws)
    key = {:device, loc}
    [{^key, old, at}] = :ets.lookup(table, key)

    if at < asked_at or not_read_yet?(old) do
      row = {key, value, now()}
      still = [{:"=:=", :"$1", {:const, old}}, {:"=:=", :"$2", at}]
      spec = [{{key, :"$1", :"$2"}, still, [{:const, row}]}]

      case :ets.select_replace(table, spec) do
        1 ->
          if old != value, do: changed(ws, {:device, loc, value})
          :ok

        0 ->
          :newer
      end
    else
      :newer
    end
  end

  defp not_read_yet?(value), do: is_binary(value) and String.ends_with?(value, "NOT READ YET)")

  @doc """
  Writes several device-status locations at once, `[{loc, value}]`, as `put_device/3` does each
  (one look-up of the table: VWS_STATUS writes seven at every poll of DAQ #1). An entry
  `{loc, value, :changed}` is a value its writer knows to be new (a reading with its own sequence
  number): announced without reading the old one back to compare. Each location at most once:
  they are written in one insert, so a reader sees all of them or none.
  """
  @spec put_devices(workstation, [{1..14, term} | {1..14, term, :changed}]) :: :ok
  def put_devices(ws, values) do
    table = table(ws)
    now = now()

    {rows, changes} =
      Enum.reduce(values, {[], []}, fn entry, {rows, changes} ->
        {loc, value, changed?} =
          case entry do
            {loc, value, :changed} when loc in 1..14 ->
              {loc, value, true}

            {loc, value} when loc in 1..14 ->
              {loc, value, :ets.lookup_element(table, {:device, loc}, 2) != value}
          end

        changes = if changed?, do: [{:device, loc, value} | changes], else: changes
        {[{{:device, loc}, value, now} | rows], changes}
      end)

    # one write of them all
    :ets.insert(table, rows)
    for change <- :lists.reverse(changes), do: changed(ws, change)
    :ok
  end

  # Change notices: the new value goes to whoever listens (`Vws.CEC.Events.notify/3`, event
  # `:mailbox`) with the system time of the write, after the write.
  defp changed(ws, change) do
    Vws.CEC.Events.notify(ws, :mailbox, {change, System.system_time(:microsecond)})
  end

  @doc """
  Keeps the latest decoded readings of a device that has no location of its own for them
  (`:pallet`: the hydraulic controller's `PALLET?` answer, clamp forces included), for the views
  (`Vws.Ops.Inspect`, the dashboard). Nothing decides on them: commands read their device.
  """
  @spec put_readings(workstation, atom, term) :: :ok
  def put_readings(ws, source, value) when is_atom(source) do
    table = table(ws)

    changed? =
      case :ets.lookup(table, {:readings, source}) do
        [{_, ^value, _}] -> false
        _ -> true
      end

    :ets.insert(table, {{:readings, source}, value, now()})
    if changed?, do: changed(ws, {:readings, source, value})
    :ok
  end

  @doc "The readings kept with `put_readings/3`: `%{source => {value, age_ms}}`."
  @spec readings(workstation) :: %{atom => {term, non_neg_integer}}
  def readings(ws) do
    now = now()

    for {{:readings, source}, value, at} <-
          :ets.match_object(table(ws), {{:readings, :_}, :_, :_}),
        into: %{},
        do: {source, {value, now - at}}
  end

  @doc "Reads a device-status location: `{value, age_ms}`; value `nil` means never written."
  @spec get_device(workstation, 1..14) :: {term, non_neg_integer}
  def get_device(ws, loc) when loc in 1..14 do
    [{_, value, at}] = :ets.lookup(table(ws), {:device, loc})
    {value, now() - at}
  end

  ## Command status (locations 34–39), CMD_IN and the command in flight

  @doc """
  Hands a command to a partition, atomically: refused with `{:busy, number}` while the partition's
  previous command is in flight, otherwise records it in flight, writes CMD_IN and sets the
  command status to `:executing`.

  Durable or refused: when the journal cannot record the dispatch, the command is not handed
  over — its status is `ERROR JOURNAL WRITE FAILED` (in memory) and the result
  `{:error, "JOURNAL WRITE FAILED"}`; it must not run.
  """
  @spec dispatch(workstation, partition, 0..9999, String.t()) ::
          :ok | {:busy, 0..9999} | {:error, String.t()}
  def dispatch(ws, partition, number, text) when partition in @partitions do
    table = table(ws)

    if :ets.insert_new(table, {{:in_flight, partition}, number}) do
      case journal(table, {:status, partition, number, :executing, text}) do
        :ok ->
          :ets.insert(table, {{:cmd_in, partition}, number, text})
          :ets.insert(table, {{:command_status, partition}, number, :executing})
          changed(ws, {:command, partition, number, :executing, text})
          :ok

        :failed ->
          :ets.insert(table, {{:cmd_in, partition}, number, text})
          :ets.insert(table, {{:command_status, partition}, number, @journal_failed})
          :ets.delete(table, {:in_flight, partition})
          changed(ws, {:command, partition, number, @journal_failed, text})
          @journal_failed
      end
    else
      case :ets.lookup(table, {:in_flight, partition}) do
        [{_, busy}] -> {:busy, busy}
        # finished between the two calls: try again
        [] -> dispatch(ws, partition, number, text)
      end
    end
  end

  @doc "The command a partition has in flight, if any."
  @spec in_flight(workstation, partition) :: 0..9999 | nil
  def in_flight(ws, partition) do
    case :ets.lookup(table(ws), {:in_flight, partition}) do
      [{_, n}] -> n
      [] -> nil
    end
  end

  @doc """
  Ends the command `number` of a partition with `status` and clears it from flight.

  The status location is only written while it still shows `number` (a newer command refused as
  busy keeps its own answer). Returns `:ok`, or `:not_in_flight` when `number` was not the
  partition's command in flight (nothing is written then).

  When the journal cannot record the end, the command ends `ERROR JOURNAL WRITE FAILED`
  instead of `status`: an end that is not on disk is never shown as DONE.
  """
  @spec finish(workstation, partition, 0..9999, :done | {:error, String.t()}) ::
          :ok | :not_in_flight
  def finish(ws, partition, number, status) do
    table = table(ws)

    case :ets.select_delete(table, [{{{:in_flight, partition}, number}, [], [true]}]) do
      1 ->
        status =
          case journal(table, {:finish, partition, number, status}) do
            :ok -> status
            :failed -> @journal_failed
          end

        if compare_and_set_status(table, partition, number, status) == 1,
          do: changed(ws, {:command, partition, number, status, nil})

        :ok

      0 ->
        :not_in_flight
    end
  end

  @doc """
  Sets the status of command `number` of a partition that is not (or no longer) run: a command
  refused by a rule of SUN_COMM. It does not touch the command in flight. A set with no
  status location (`:status`, `:ack`) keeps none: nothing is written. A status the journal
  could not record reads `ERROR JOURNAL WRITE FAILED`.
  """
  @spec put_status(workstation, partition | atom, 0..9999, status) :: :ok
  def put_status(ws, partition, number, status) when partition in @partitions do
    table = table(ws)

    status =
      case journal(table, {:status, partition, number, status}) do
        :ok -> status
        :failed -> @journal_failed
      end

    :ets.insert(table, {{:command_status, partition}, number, status})
    changed(ws, {:command, partition, number, status, nil})
    :ok
  end

  def put_status(_ws, set, _number, _status) when is_atom(set), do: :ok

  @doc """
  Attaches the recorder (a `Vws.CEC.Mailbox.Recorder`, `Vws.CEC.Journal`) that is given
  every change before it is visible.
  """
  @spec attach_recorder(:ets.tid(), module) :: :ok
  def attach_recorder(table, module) when is_atom(module) do
    :ets.insert(table, {:recorder, module})
    :ok
  end

  @doc """
  Gives `record` to the table's recorder (`attach_recorder/2`): `:ok` when it is durable or there
  is no recorder, `{:error, reason}` when it could not be made durable. Used by everything that
  keeps its state in the mailbox table (the interlock's leases too).
  """
  @spec record(:ets.tid(), tuple) :: :ok | {:error, term}
  def record(table, record) do
    case :ets.lookup(table, :recorder) do
      [] -> :ok
      [{:recorder, module}] -> module.record(table, record)
    end
  end

  defp store_lines(table, key, lines) do
    case :ets.lookup(table, :recorder) do
      [] -> :ok
      [{:recorder, module}] -> module.store_lines(table, key, lines)
    end
  end

  # Durable before visible: the journal (when the workstation has one) gets the change first;
  # :failed when it could not be made durable (the journal has logged why).
  defp journal(table, record) do
    case record(table, record) do
      :ok ->
        :ok

      {:error, reason} ->
        Logger.error(
          "journal write failed (#{inspect(reason)}): ends ERROR JOURNAL WRITE FAILED: " <>
            inspect(record, limit: 8)
        )

        :failed
    end
  end

  @doc """
  Sets the status of command `number` of a set letter the CEC does not know (rule broken
  `UNKNOWN COMMAND SET <letter>`), answered to the status `<letter>_CMD`.
  """
  @spec put_unknown_status(workstation, String.t(), 0..9999, status) :: :ok
  def put_unknown_status(ws, letter, number, status) do
    table = table(ws)

    status =
      case journal(table, {:unknown_status, letter, number, status}) do
        :ok -> status
        :failed -> @journal_failed
      end

    :ets.insert(table, {{:unknown_status, letter}, number, status})
    :ok
  end

  @doc """
  The status of the last command of an unknown set letter: `{number | nil, status}`; for a
  letter never seen `{nil, :none}` — or `{nil, {:no_data, why}}` when a damaged journal could
  not tell whether one was seen.
  """
  @spec unknown_status(workstation, String.t()) :: {0..9999 | nil, status}
  def unknown_status(ws, letter) do
    table = table(ws)

    case :ets.lookup(table, {:unknown_status, letter}) do
      [{_, number, status}] -> {number, status}
      [] -> {nil, unknown_default(table)}
    end
  end

  defp unknown_default(table) do
    case :ets.lookup(table, :unknown_status_default) do
      [{_, status}] -> status
      [] -> :none
    end
  end

  @doc "The command status of a partition: `{number | nil, status}`."
  @spec command_status(workstation, partition) :: {0..9999 | nil, status}
  def command_status(ws, partition) do
    [{_, number, status}] = :ets.lookup(table(ws), {:command_status, partition})
    {number, status}
  end

  @doc "CMD_IN of a partition: `{number, text}` of its latest command (`{nil, nil}` before any)."
  @spec cmd_in(workstation, partition) :: {0..9999 | nil, String.t() | nil}
  def cmd_in(ws, partition) do
    [{_, number, text}] = :ets.lookup(table(ws), {:cmd_in, partition})
    {number, text}
  end

  defp compare_and_set_status(table, partition, number, status) do
    key = {:command_status, partition}
    :ets.select_replace(table, [{{key, number, :_}, [], [{{{key}, number, {:const, status}}}]}])
  end

  ## The last command string (retransmission rule)

  @doc "Remembers the sequence number and bytes of the last accepted command string."
  @spec put_last_string(workstation, 0..9999, binary) :: :ok
  def put_last_string(ws, seq, line) do
    :ets.insert(table(ws), {:last_string, seq, line})
    :ok
  end

  @doc """
  The last accepted command string: `{seq, line}`, `{nil, nil}` (none yet) or `{:unknown, nil}`
  (the journal that held it was damaged: `Vws.CEC.Journal.Replay`).
  """
  @spec last_string(workstation) :: {0..9999 | nil | :unknown, binary | nil}
  def last_string(ws) do
    [{_, seq, line}] = :ets.lookup(table(ws), :last_string)
    {seq, line}
  end

  ## NC file and NC_UP

  @doc """
  Replaces the NC file (the program downloaded from the WC). With a journal the program is on
  disk first (the recorder's `store_lines`, `Vws.CEC.Journal.store_lines/3`); `{:error, reason}` when it could not be made durable
  (the mailbox keeps the old program then). `from`: `{:library, name, version, digest}` when
  these lines are that version of the program library already (DOWNLOAD_HP): the recorder
  keeps the reference, not a second copy.
  """
  @spec put_nc_file(workstation, [binary], nil | {:library, String.t(), pos_integer, binary}) ::
          :ok | {:error, term}
  def put_nc_file(ws, lines, from \\ nil), do: put_lines(ws, :nc_file, lines, from || lines)

  @doc "The NC file's lines."
  @spec nc_file(workstation) :: [binary]
  def nc_file(ws), do: get_lines(ws, :nc_file)

  @doc "Replaces NC_UP (the program uploaded from the machine tool); durable like `put_nc_file/2`."
  @spec put_nc_up(workstation, [binary]) :: :ok | {:error, term}
  def put_nc_up(ws, lines), do: put_lines(ws, :nc_up, lines, lines)

  @doc "NC_UP's lines."
  @spec nc_up(workstation) :: [binary]
  def nc_up(ws), do: get_lines(ws, :nc_up)

  defp put_lines(ws, key, lines, durable) when is_list(lines) do
    table = table(ws)

    case store_lines(table, key, durable) do
      :ok ->
        :ets.insert(table, {key, lines})
        :ok

      {:error, reason} = error ->
        Logger.error("#{key} not stored durably (#{inspect(reason)}): kept the old one")
        error
    end
  end

  defp get_lines(ws, key) do
    [{_, lines}] = :ets.lookup(table(ws), key)
    lines
  end

  ## Dump and load (for the journal)

  @typedoc "The restorable part of the mailboxes (`dump/1`)."
  @type dump :: %{
          partitions: %{
            partition => %{
              number: 0..9999 | nil,
              status: status,
              cmd_in: {0..9999 | nil, String.t() | nil}
            }
          },
          last_string: {non_neg_integer | nil | :unknown, binary | nil},
          unknown: %{String.t() => {0..9999 | nil, status}},
          unknown_default: status
        }

  @doc """
  The restorable part of the mailboxes: per partition its last command's number and status and
  its CMD_IN, the last string, and the statuses of unknown set letters (`unknown_default`: that
  of a letter never seen, `:none` unless a damaged journal could not tell).
  """
  @spec dump(:ets.tid()) :: dump
  def dump(table) do
    partitions =
      Map.new(@partitions, fn p ->
        [{_, number, status}] = :ets.lookup(table, {:command_status, p})
        [{_, in_number, in_text}] = :ets.lookup(table, {:cmd_in, p})
        {p, %{number: number, status: status, cmd_in: {in_number, in_text}}}
      end)

    [{_, seq, line}] = :ets.lookup(table, :last_string)

    unknown =
      for {{:unknown_status, letter}, n, status} <-
            :ets.match_object(table, {{:unknown_status, :_}, :_, :_}),
          into: %{},
          do: {letter, {n, status}}

    %{
      partitions: partitions,
      last_string: {seq, line},
      unknown: unknown,
      unknown_default: unknown_default(table)
    }
  end

  @doc "Writes a `dump/1` back into the mailboxes (nothing is recorded)."
  @spec load(:ets.tid(), dump) :: :ok
  def load(table, %{partitions: partitions, last_string: {seq, line}, unknown: unknown} = dump) do
    for {p, %{number: number, status: status, cmd_in: {in_n, in_text}}} <- partitions do
      :ets.insert(table, {{:command_status, p}, number, status})
      :ets.insert(table, {{:cmd_in, p}, in_n, in_text})
    end

    :ets.insert(table, {:last_string, seq, line})

    :ets.match_delete(table, {{:unknown_status, :_}, :_, :_})

    for {letter, {n, status}} <- unknown,
        do: :ets.insert(table, {{:unknown_status, letter}, n, status})

    :ets.insert(table, {:unknown_status_default, Map.get(dump, :unknown_default, :none)})
    :ok
  end

  @doc "The status word of a command status as the WC reads it."
  @spec status_word(status) :: String.t()
  defdelegate status_word(status), to: Vws.Codecs.WC.Status, as: :word

  @doc """
  A device-status value in words, as a person reads it: the text itself; `{:no_data, why}` as
  `NO DATA (why)`; a poll of DAQ #1 (`Vws.Links.DAQ.Readings`, location 11) as its quantities
  (`Vws.Links.DAQ.Readings.describe/1`); nil (never written) as nil.

      iex> Vws.CEC.Mailbox.device_text({:no_data, "NO LINK TO DAQ #1"})
      "NO DATA (NO LINK TO DAQ #1)"
  """
  @spec device_text(term) :: String.t() | nil
  def device_text(nil), do: nil

  def device_text(v) when is_binary(v),
    do: if(String.printable?(v), do: v, else: "UNPRINTABLE TEXT #{Base.encode16(v)}")

  def device_text({:no_data, why}) when is_binary(why),
    do: Vws.Links.DAQ.DeviceStatus.no_data(why)

  def device_text(%Vws.Links.DAQ.Readings{} = r), do: Vws.Links.DAQ.Readings.describe(r)
  def device_text(other), do: "UNKNOWN VALUE " <> Vws.Codecs.WC.Words.of(other)

  defp now, do: System.monotonic_time(:millisecond)
end
