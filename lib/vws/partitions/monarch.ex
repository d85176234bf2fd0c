defmodule Vws.Partitions.Monarch do
  @moduledoc """
  MONARCH (seed §3, Fig. 7, App. I A): runs the Monarch command set on the GE-2000 through the
  DNC Level 2 link given as the partition's `link` (a `Vws.Links.DNC` process or its name).

  | command | on the link | result |
  |---------|-------------|--------|
  | `DOWNLOAD_GE` | `SNS` + the NC file, then `RNF` | the GE-2000 files it as `nnnnnn.PRO` (first `O`/`:` word); its directory entry must match the bytes sent |
  | `UPLOAD_GE(nnnnnn.PRO\\|.GSU)` | `RNS` + file name | the program replaces NC_UP, whole (ending in `%`) or not at all |
  | `PROGRAM_SELECT(nnnnnn)` | `SNK` + `nnnnnn.PRO` | selected for the next cycle start |
  | `PROGRAM_DELETE(nnnnnn.PRO\\|.GSU)` | `SND` + file name | deleted |
  | `TABLE(L1/…/Ln)` | `RNO` + `TOFFSET` | the offsets of lines L1…Ln → `TLI_TABLE` status `n/M1/…/Mn` |
  | `DRIP_FEED` | `SCE` + the NC file, then `RNL` | drip feed (ours): the GE-2000 runs the program while it arrives, pausing the CEC with WACK; DONE once the whole program has reached the machine (it may still be running) |
  | `STATUS` | `RNL` | `MONARCH` status `ACTIVE` or `IDLE` |
  | `CYCLE_START` | (DAQ #1 relay) then `RNL` | DONE once the machine reports ACTIVE |
  | `RELEASE_TABLE` | `RNL` | clears the table interlock; refused `ERROR MACHINE ACTIVE` |

  From the program library (`Vws.CEC.Library`, ours — issue 18; the workstation's `library:`):

  | command | on the link | result |
  |---------|-------------|--------|
  | `DOWNLOAD_GE(nnnnnn.PRO)` / `DOWNLOAD_GE(nnnnnn.PRO/v)` | `SCS`/`SNS` with the file name as command text + the program, then `RNL`, `RNF` | the library's latest released version (or version v, whatever its origin) filed under that name, verified like DOWNLOAD_GE; `ERROR nnnnnn.PRO HAS NO RELEASED VERSION` when every version came from the machine |
  | `DRIP_FEED(nnnnnn.PRO[/v][/Nk])` | `SCE` + the program from line k, then `RNL` | drip feed of the library's latest released version (or version v) — no copy through the WC link — restarted at line k with the modal state of the lines before it restored (`restart/4`, `Vws.Codecs.NCModal`; logged before it is sent); `ERROR RESTART LINE k BEYOND THE END …`, `… INSIDE A CANNED CYCLE …` send nothing |
  | `COMPARE_GE` | `RNF` | the machine's directory recorded in the library: each program `same`/`differs`/`absent` |
  | `COMPARE_GE(nnnnnn.PRO)` | `RNF`, then `RNS` + file name | DONE only when the machine holds exactly a version of the program, every byte read back (its SHA-256 digest that of a version); else `ERROR PROGRAM ABSENT nnnnnn.PRO`, `ERROR PROGRAM DIFFERS nnnnnn.PRO` |

  A program the operator sends from the machine unasked goes to the library as a version from
  the machine, not released (`store_from_machine/3`), never to NC_UP: NC_UP holds only what
  `UPLOAD_GE` brought.

  Every directory MONARCH reads (also after each DOWNLOAD_GE) is recorded in the library, so
  the dashboard and `mix vws.library` show where each program stands; `compare/2` does the
  same from iex.

  `DOWNLOAD_HP` and `UPLOAD_SUN` are transfers on the WC link, carried out by SUN_COMM; they
  never reach this partition.

  **Hardware handshaking.** After each `S` command (`SNS`, `SNK`, `SND`) MONARCH reads the status
  report (`RNL`) and ends the command `ERROR GE-2000 ALARM n` unless the alarm is 0 (and, for a
  select, the report names the program). Every status report read also refreshes the `MONARCH`
  device status (location 8). Option `verify: false` skips the extra report.

  **A program is whole or it is nothing** (PROTOCOLS.md §2). DOWNLOAD_GE sends only an NC file
  that ends with its `%` line, and after the status report reads the directory (`RNF`): unless
  the entry of `nnnnnn.PRO` has the size and CRC-16/ARC of exactly the bytes sent, the command
  ends `ERROR PROGRAM VERIFY FAILED nnnnnn.PRO` — DONE means the machine holds those bytes. An
  UPLOAD_GE whose text does not end with a `%` line (the transmission ended early: an ENQ
  damaged into EOT looks like a normal end) ends `ERROR PROGRAM INCOMPLETE` and NC_UP keeps the
  old program. (`verify: false` skips the directory too.)

  **Program size limit** (PROTOCOLS.md §2): the directory's size field has six digits, so
  DOWNLOAD_GE, DOWNLOAD_GE(nnnnnn.PRO[/v][/FORCE]), a remote request, UPLOAD_GE and a program the
  machine sends unasked are refused over 999,999 bytes, before a byte is sent or stored: `ERROR
  PROGRAM TOO LARGE <bytes> BYTES (LIMIT 999999)` (`Vws.Links.DNC.Program.check_size/1`, the one
  home of the limit). DRIP_FEED stores nothing and has no limit: the library keeps programs of
  up to 64 MiB (`Vws.CEC.Library.max_bytes/0`) for it.

  **Table interlock** (seed App. I A, §2.3.8 rules 1b and 3b), decided for every command by the
  one interlock table, `Vws.CEC.Interlock.Rules`: CYCLE_START and DRIP_FEED — both set the
  machine moving — first take the table's work volume for the machine (holder `:monarch`,
  reason `:cycle`), re-tried four times a second while the robot or the vise holds it, until
  `interlock: [timeout: ms]` (default 10 000) ends the command `ERROR INTERLOCK TABLE HELD BY
  ROBOT` (or `FIXTURE`) before a byte is sent or the relay closed — so the vise may not open
  nor the robot approach the table. CYCLE_START then closes the cycle-start relay of DAQ #1
  through the `:cycle_start` option, a function `(-> :ok | {:error, reason})` (without it
  CYCLE_START ends `ERROR NO LINK TO DAQ #1` and takes nothing: `missing_link/2`). The machine
  keeps the table, whatever became of the start or the feed, until RELEASE_TABLE gives it up
  once the machine reports IDLE. A program the operator sends from the machine starts nothing.

  **Following the machine.** The `MONARCH` status is kept current without the WC asking:
  `Vws.Partitions.Monarch.Monitor`, started with the DNC link by the workstation's `devices:`
  option, reads the status report every second (as VWS_STATUS reads DAQ #1), so the WC follows a
  cycle — and finds the machine IDLE before its first Monarch command — with `S MONARCH` alone.

  ## A transmission the line broke off

  The DNC link resends a block at most three times (PROTOCOLS.md §2); a transmission that still
  fails leaves nothing behind on either side. A request that has the same effect once or twice —
  reading a report, a table or a program, storing a whole program (it replaces the file),
  selecting one — is then made again, at most twice more (`[:vws, :monarch, :request_again]`);
  a delete is not, nor a request refused for good (link down, peer busy, bad text). After the
  cycle-start button, the machine's reports are read until one says ACTIVE or the time is up.

  ## Options (`partitions: [monarch: [options: …]]`)

    * `:cycle_start` — the relay function above
    * `:check` — `:crc` (default, commands `SC…`/`RC…`) or `:lrc` (`SN…`/`RN…`, as the seed's
      dialogues show). CRC is the default because two bit errors in the same position of a block
      cancel in the LRC's XOR: under line faults (BER 1.5e-3) LRC let corrupted programs through
      as complete, CRC never did.
    * `:verify` — read the status report after S commands (default true)
    * `:start_timeout` — ms for the machine to report ACTIVE after the relay (10 000)
    * `:poll_interval` — ms between status reports while waiting for it (100)
    * `:request_timeout` — bound on one DNC request (`:infinity`: the link's limits end it)
    * `:interlock` — `timeout` (ms, default 10 000) and `retry_ms` (250) of the table's lease
    * `:profile` — the DNC port's profile (`Vws.Links.ProgramPort.Profile`, set by the
      workstation's `devices:`): `:ge2000_level2` (default, `Vws.Links.DNC`) or `:rs232_xonxoff`
      (`Vws.Links.RS232`, docs/serial.md). On a plain RS-232 control DOWNLOAD_GE,
      DOWNLOAD_GE(nnnnnn.PRO[/v]), UPLOAD_GE, DRIP_FEED and programs from the machine work (a
      download DONE only when the control's read-back is the bytes sent; there is no status
      report, so `verify` defaults to false); COMPARE_GE(nnnnnn.PRO) compares the program the
      control punches back; STATUS, PROGRAM_SELECT, PROGRAM_DELETE, TABLE, COMPARE_GE, CYCLE_START
      and RELEASE_TABLE end `ERROR` with what the control cannot do (`NO STATUS REPORT FROM AN
      RS-232 CONTROL`, …) — the table stays held after a drip feed until the machine's state can
      be read.
  """
  # a request the line broke off is made again (see send_request/5): this many tries in all
  @request_tries 3
  # a delete finds no file the second time; a drip-fed program has run in part
  @not_again [:delete, :download_execute]
  @broken_off [:nak_limit, :no_reply, :aborted, :no_response, :receive_timeout, :no_answer_to_bid]

  @behaviour Vws.CEC.Partition.CommandSet
  require Logger

  alias Vws.Links.DNC
  alias Vws.Links.DNC.{Frame, LinkError, Program, Report}
  alias Vws.Links.DNC.Frame.Command
  alias Vws.CEC.{Interlock, Mailbox}
  alias Vws.Partitions.Monarch.Transfers

  @monarch_location 8
  @tli_location 6

  @impl true
  def device, do: "GE-2000"

  @impl true
  def parse(text), do: Vws.Codecs.Commands.parse(:monarch, text)

  @doc "CYCLE_START needs the cycle-start relay on DAQ #1 (the `:cycle_start` option) too."
  @impl true
  def missing_link(:cycle_start, ctx),
    do: if(is_function(ctx.options[:cycle_start], 0), do: nil, else: "DAQ #1")

  def missing_link(_command, _ctx), do: nil

  @impl true
  def execute(command, ctx)

  # every transfer a command makes is recorded at its end, with its result (issue 27: the one
  # home of the transfer history, Vws.Partitions.Monarch.Transfers); then the command runs
  def execute(command, ctx) when not is_map_key(ctx, :transfers) do
    Transfers.command(ctx, fn -> execute(command, Map.put(ctx, :transfers, :recorded)) end)
  end

  def execute(command, _ctx) when command in [:download_hp, :upload_sun],
    do: {:error, "#{command |> to_string() |> String.upcase()} IS CARRIED OUT BY SUN_COMM"}

  def execute({:download_hp, _crc}, ctx), do: execute(:download_hp, ctx)

  def execute(:download_ge, ctx) do
    with {:ok, file, text} <- nc_file_program(ctx.workstation),
         # no larger than the machine can store: refused before a byte is sent
         :ok <- Program.check_size(text),
         :ok <- send_program(ctx, :part_program, "", text, "DOWNLOAD OF #{file} FAILED"),
         :ok <- verify_directory(ctx, file, text),
         do: :done
  end

  def execute({:download_ge, file, which}, ctx) do
    with {:ok, text} <- library_program(ctx.workstation, file, which, :to_send),
         :ok <- Program.check_size(text),
         :ok <- if(Program.complete?(text), do: :ok, else: {:error, "#{file} HAS NO CLOSING %"}),
         :ok <-
           if(Program.sendable?(text),
             do: :ok,
             else: {:error, "#{file} HOLDS A CONTROL CHARACTER"}
           ),
         :ok <- send_program(ctx, :part_program, file, text, "DOWNLOAD OF #{file} FAILED"),
         :ok <- verify_directory(ctx, file, text),
         do: :done
  end

  # Drip feed (ours, docs/dnc-drip-feed.md): the NC file goes as one E (download and execute)
  # transmission that the machine runs while it arrives, pausing the CEC with WACK when its
  # buffer is full. Never made again when the line breaks it off: the machine has run part of it.
  def execute(:drip_feed, ctx) do
    with {:ok, file, text} <- nc_file_program(ctx.workstation),
         :ok <- send_program(ctx, :download_execute, file, text, "DRIP FEED OF #{file} FAILED"),
         do: :done
  end

  # Ours (issue 27): a library program drip-fed — no copy through the WC link — from its first
  # line or restarted at line k with the modal state of the lines before it restored
  # (Vws.Codecs.NCModal); the restored preamble is logged before a byte is sent.
  def execute({:drip_feed, file, which, line}, ctx) do
    with {:ok, lines, version, preamble} <- restart(ctx.workstation, file, which, line) do
      if line > 1, do: log_restart(ctx.workstation, file, version, line, preamble)
      text = Program.to_text(lines)

      result = send_program(ctx, :download_execute, file, text, "DRIP FEED OF #{file} FAILED")
      # the history's record says what the bytes are: no version holds them
      if line > 1, do: Transfers.note("version #{version} restarted at line #{line}")
      with :ok <- result, do: :done
    end
  end

  def execute(:compare_ge, ctx) do
    with {:ok, _entries} <- directory(ctx), do: :done
  end

  # The directory (size, CRC-16) finds the versions the machine may hold; the read-back's
  # SHA-256 digest says which one it holds, if any.
  # A plain RS-232 control has no directory (Vws.Links.RS232): the program it punches back is
  # compared whole.
  def execute({:compare_ge, file}, ctx) do
    with {:ok, versions} <- library_versions(ctx.workstation, file),
         {:ok, entries} <-
           if(profile(ctx) == :rs232_xonxoff, do: {:ok, :none}, else: directory(ctx)) do
      case entries != :none and Vws.CEC.Library.on_machine(versions, Map.get(entries, file)) do
        # nothing to read back: said in words, nothing sent
        :absent ->
          {:error, "PROGRAM ABSENT #{file}"}

        # the same, ambiguous, or different: read back, and a difference said line by line
        _ ->
          case read_back(ctx, file, versions) do
            {:same, n} ->
              Transfers.note("same as v#{n}")
              :done

            :differs ->
              differs(ctx.workstation, file)

            {:error, _} = error ->
              error
          end
      end
    end
  end

  def execute({:upload_ge, file}, ctx) do
    with {:ok, blocks} <- request(ctx, :receive, :part_program, file, []),
         text = IO.iodata_to_binary(blocks),
         :ok <- if(text == "", do: {:error, "GE-2000 SENT NO PROGRAM #{file}"}, else: :ok),
         :ok <- Program.check_size(text),
         :ok <- if(Program.complete?(text), do: :ok, else: {:error, "PROGRAM INCOMPLETE"}),
         lines = Program.from_text(text),
         :ok <- uploadable(lines, file) do
      case Mailbox.put_nc_up(ctx.workstation, lines) do
        :ok -> :done
        {:error, reason} -> {:error, "NC_UP NOT STORED #{words(reason)}"}
      end
    end
  end

  def execute({:program_select, number}, ctx) do
    with {:ok, _} <- request(ctx, :send, :remote_control, number <> ".PRO", []),
         {:ok, _} <-
           verify(ctx, "PROGRAM #{number} NOT SELECTED", &(&1.program == number)) do
      :done
    end
  end

  def execute({:program_delete, file}, ctx) do
    with {:ok, _} <- request(ctx, :send, :delete, file, []),
         {:ok, _} <- verify(ctx, "#{file} NOT DELETED", fn _ -> true end) do
      :done
    end
  end

  def execute({:table, wanted}, ctx) do
    with {:ok, blocks} <- request(ctx, :receive, :table, "TOFFSET", []),
         {:ok, table} <- offsets(blocks),
         {:ok, values} <- select_offsets(table, wanted) do
      text = Enum.join([Integer.to_string(length(values)) | values], "/")
      Mailbox.put_device(ctx.workstation, @tli_location, text)
      :done
    end
  end

  def execute(:status, ctx) do
    with {:ok, _report} <- status_report(ctx), do: :done
  end

  # The table was taken for the machine (:cycle) by the interlock table, Vws.CEC.Interlock.Rules.
  def execute(:cycle_start, ctx) do
    case ctx.options[:cycle_start].() do
      :ok ->
        deadline = now() + Keyword.get(ctx.options, :start_timeout, 10_000)
        await_active(ctx, deadline)

      {:error, reason} ->
        {:error, "CYCLE START RELAY FAILED #{reason_text(reason)}"}
    end
  end

  def execute(:release_table, ctx) do
    case status_report(ctx) do
      {:ok, %{state: :active}} ->
        {:error, "MACHINE ACTIVE"}

      {:ok, %{state: :idle}} ->
        Interlock.release(ctx.workstation, :table, :monarch)
        :done

      error ->
        error
    end
  end

  ## Steps

  # The button was pressed: the machine's reports are read until one says ACTIVE. One that
  # cannot be read is read again while there is time (the table stays MONARCH's if none can).
  defp await_active(ctx, deadline) do
    case status_report(ctx) do
      {:ok, %{state: :active}} ->
        :done

      other ->
        if now() >= deadline do
          with {:ok, report} <- other,
               do: {:error, "MACHINE DID NOT START (ALARM #{report.alarm})"}
        else
          Process.sleep(Keyword.get(ctx.options, :poll_interval, 100))
          await_active(ctx, deadline)
        end
    end
  end

  # Hardware handshaking after an S command: the machine's own report must agree.
  defp verify(ctx, what, ok?) do
    if verify?(ctx) do
      with {:ok, report} <- status_report(ctx) do
        cond do
          report.alarm != 0 -> {:error, "#{what} GE-2000 ALARM #{report.alarm}"}
          not ok?.(report) -> {:error, what}
          true -> {:ok, report}
        end
      end
    else
      {:ok, nil}
    end
  end

  # The machine's directory must hold exactly the bytes sent under the file's name.
  defp verify_directory(ctx, file, text) do
    if verify?(ctx) do
      sent = Report.entry(file, text)

      case read_directory(ctx) do
        {:ok, %{^file => ^sent}} -> :ok
        {:ok, _other} -> {:error, "PROGRAM VERIFY FAILED #{file}"}
        {:error, :bad_directory} -> {:error, "PROGRAM VERIFY FAILED #{file} BAD DIRECTORY"}
        {:error, _} = error -> error
      end
    else
      :ok
    end
  end

  # RNF → the directory, recorded in the program library (when the workstation has one).
  # the directory for a command's own use: one none of whose lines names a file said in words
  defp directory(ctx) do
    case read_directory(ctx) do
      {:error, :bad_directory} -> {:error, "BAD DIRECTORY FROM GE-2000"}
      other -> other
    end
  end

  defp read_directory(ctx) do
    with {:ok, blocks} <- request(ctx, :receive, :directory, "", []) do
      case Report.parse_directory(IO.iodata_to_binary(blocks)) do
        {:ok, entries} ->
          if Vws.CEC.Library.enabled?(ctx.workstation) do
            with {:error, reason} <-
                   Vws.CEC.Library.record_machine(ctx.workstation, entries) do
              require Logger

              Logger.error(
                "program library: the machine's directory not recorded: #{inspect(reason)}"
              )
            end
          end

          {:ok, entries}

        {:error, _} ->
          {:error, :bad_directory}
      end
    end
  end

  # What differs, in a status the WC can take (94 characters at most): the line counts and
  # the first line; the whole line diff is the history's note's and `mix vws.library diff
  # --machine`'s (docs/program-library.md "Line diff").
  defp differs(ws, file) do
    case Vws.CEC.Library.diff_machine(ws, file) do
      {:ok, %{version: v, summary: %{removed: 0, added: 0}}} ->
        Transfers.note("differs from v#{v.version} in its bytes, not its lines")
        {:error, "PROGRAM DIFFERS #{file} FROM V#{v.version} IN BYTES NOT LINES"}

      {:ok, %{version: v, summary: %{removed: r, added: a, first_line: l}}} ->
        Transfers.note(
          "differs from v#{v.version}: #{r} lines removed, #{a} added, first at line #{l}"
        )

        {:error, "PROGRAM DIFFERS #{file} FROM V#{v.version} LINES -#{r} +#{a} AT LINE #{l}"}

      _ ->
        {:error, "PROGRAM DIFFERS #{file}"}
    end
  end

  # RNS → every byte of the file: `{:same, n}` for the version of the library that holds exactly
  # these bytes (the same SHA-256 digest, and its file reads whole), else `:differs`.
  defp read_back(ctx, file, versions) do
    with {:ok, blocks} <- request(ctx, :receive, :part_program, file, []) do
      bytes = IO.iodata_to_binary(blocks)
      digest = Vws.CEC.Library.digest(bytes)

      # what the machine holds, kept for the line diff (Library.diff_machine/3)
      with {:error, reason} <- Vws.CEC.Library.record_read_back(ctx.workstation, file, bytes) do
        Logger.error("program library: the read-back of #{file} not kept: #{inspect(reason)}")
      end

      case Vws.CEC.Library.same_as(versions, digest) do
        {:ok, v} ->
          with {:ok, _text} <- library_program(ctx.workstation, file, v.version),
               do: {:same, v.version}

        :none ->
          :differs
      end
    end
  end

  defp library_program(ws, file, which, purpose \\ :to_compare)

  # DOWNLOAD_GE(nnnnnn.PRO/v/FORCE): version v whatever its workflow state (issue 27)
  defp library_program(ws, file, {:force, n}, _purpose), do: library_program(ws, file, n)

  defp library_program(ws, file, which, purpose) do
    case Vws.CEC.Library.read(ws, file, which) do
      # only released versions go to a machine unless the command says FORCE
      {:ok, _text, %{released: false}} when purpose == :to_send ->
        {:error, "#{file} VERSION #{which} NOT RELEASED"}

      {:ok, text, _version} ->
        {:ok, text}

      {:error, reason} ->
        {:error, library_error(file, which, reason)}
    end
  end

  @doc """
  The drip feed `DRIP_FEED(file[/v]/Nline)` would send, before it is sent (iex, `mix vws.library`):
  `{:ok, lines, version, preamble}` — the program restarted at `line` (`Vws.Codecs.NCModal.restart/2`),
  the library version it comes from, and the lines that restore the modal state — or
  `{:error, words}` as the command would end.
  """
  @spec restart(Mailbox.workstation(), String.t(), :latest | pos_integer, pos_integer) ::
          {:ok, [String.t()], pos_integer, [String.t()]} | {:error, String.t()}
  def restart(ws, file, which, line) do
    with {:ok, text, v} <- released_read(ws, file, which),
         :ok <- whole_and_sendable(file, text),
         {:ok, preamble, lines} <- Vws.Codecs.NCModal.restart(Program.from_text(text), line) do
      {:ok, lines, v.version, preamble}
    end
  end

  @doc """
  The program a machine may be sent unasked by the WC (a remote request from the machine's panel,
  `Vws.Partitions.Monarch.RemoteRequest`): the library's latest released version of `file`, or
  version `which` only if it is released — `{:ok, text, version}`, or `{:error, words}` (no such
  program or version, not released, too large, not whole, a control character).
  """
  @spec released_program(Mailbox.workstation(), String.t(), :latest | pos_integer) ::
          {:ok, binary, pos_integer} | {:error, String.t()}
  def released_program(ws, file, which) do
    with {:ok, text, v} <- released_read(ws, file, which),
         :ok <- Program.check_size(text),
         :ok <- whole_and_sendable(file, text),
         do: {:ok, text, v.version}
  end

  @doc """
  After a program went to the machine other than by `DOWNLOAD_GE` (a remote request): the same
  check as `DOWNLOAD_GE`'s — the status report (no alarm), then the directory entry of `file`
  has the size and CRC-16 of `text` (the directory is recorded in the library). `:ok` or
  `{:error, words}`. Options as the partition's (`:check`, `:request_timeout`, `:verify`).
  """
  @spec verify_download(Mailbox.workstation(), DNC.link(), String.t(), binary, keyword) ::
          :ok | {:error, String.t()}
  def verify_download(ws, link, file, text, options \\ []) do
    ctx = %{workstation: ws, link: link, options: options}

    with {:ok, _report} <- verify(ctx, "DOWNLOAD OF #{file} FAILED", fn _ -> true end),
         do: verify_directory(ctx, file, text)
  end

  defp whole_and_sendable(file, text) do
    cond do
      not Program.complete?(text) -> {:error, "#{file} HAS NO CLOSING %"}
      not Program.sendable?(text) -> {:error, "#{file} HOLDS A CONTROL CHARACTER"}
      true -> :ok
    end
  end

  defp log_restart(ws, file, version, line, preamble) do
    Logger.info(
      "MONARCH: DRIP_FEED of #{file} version #{version} restarted at line #{line}, " <>
        "modal state restored by: #{Enum.join(preamble, " / ")}"
    )

    Vws.Telemetry.execute([:vws, :monarch, :drip_restart], %{line: line}, %{
      workstation: ws,
      program: file,
      version: version,
      preamble: preamble
    })
  end

  # a version that may go to a machine: released (the latest released one for :latest), as
  # DOWNLOAD_GE(nnnnnn.PRO/v) without FORCE
  defp released_read(ws, file, which) do
    case library_read(ws, file, which) do
      {:ok, _text, %{released: false} = v} ->
        {:error, "#{file} VERSION #{v.version} NOT RELEASED"}

      other ->
        other
    end
  end

  defp library_read(ws, file, which) do
    case Vws.CEC.Library.read(ws, file, which) do
      {:ok, text, v} -> {:ok, text, v}
      {:error, reason} -> {:error, library_error(file, which, reason)}
    end
  end

  defp library_versions(ws, file) do
    case Vws.CEC.Library.versions(ws, file) do
      {:ok, versions} -> {:ok, versions}
      {:error, reason} -> {:error, library_error(file, :latest, reason)}
    end
  end

  defp library_error(_file, _which, :no_library), do: "NO PROGRAM LIBRARY"
  defp library_error(file, :latest, :not_found), do: "#{file} NOT IN LIBRARY"
  defp library_error(file, :latest, :not_released), do: "#{file} HAS NO RELEASED VERSION"
  defp library_error(file, n, :not_found), do: "#{file} VERSION #{n} NOT IN LIBRARY"
  defp library_error(file, _which, :damaged), do: "LIBRARY FILE OF #{file} DAMAGED"
  defp library_error(file, n, :deleted), do: "#{file} VERSION #{n} DELETED"

  defp library_error(file, _which, reason),
    do: "#{file} NOT READ FROM LIBRARY #{words(reason)}"

  # A reason in upper-case words and numbers for an ERROR status (never an Elixir term):
  # {:journal, :enospc} → "JOURNAL ENOSPC".
  defp words(reason) when is_binary(reason),
    do: reason |> String.upcase() |> String.replace(~r/[^A-Z0-9 .\/-]+/, " ") |> String.trim()

  defp words(reason) when is_atom(reason), do: reason |> Atom.to_string() |> words()
  defp words(reason) when is_integer(reason), do: Integer.to_string(reason)

  defp words(reason) when is_tuple(reason),
    do: reason |> Tuple.to_list() |> Enum.map_join(" ", &words/1)

  defp words(_reason), do: "FAILED"

  @doc """
  Compares the program library of workstation `ws` with what its GE-2000 holds, from iex: reads
  the machine's directory (`RNF`) through `ws`'s DNC link, records it in the library, and returns
  `Vws.CEC.Library.compare/1` — each program `on_machine` `{:same, version}`, `:differs` or
  `:absent`. With `read_back: true` (every program the directory shows the same) or
  `read_back: [file names]` those programs are also read back whole (`RNS`) and compared byte for
  byte: each such row gets `read_back: :same | :differs` (a `:differs` also makes it `on_machine:
  :differs`; a `:same` names the version the bytes are: their SHA-256 digest's). A program whose
  directory entry has the size and CRC-16 of versions that differ (`{:ambiguous, [n]}`) is
  always read back. `Vws.Ops.LibraryText.print_compare/1` prints the result.

  Options: `:link` (default the workstation's GE-2000 link), `:check`, `:request_timeout`,
  `:requester` (who asked, for the transfer history: default `"iex"`).
  """
  @spec compare(Mailbox.workstation(), keyword) :: {:ok, map} | {:error, term}
  def compare(ws, opts \\ []) do
    link = Keyword.get_lazy(opts, :link, fn -> Vws.Names.whereis(ws, :ge2000) end)
    # (who asked, for the transfer history of its read-backs)
    ctx = %{workstation: ws, link: link, options: opts, requester: opts[:requester] || "iex"}

    with :ok <- if(link, do: :ok, else: {:error, "NO LINK TO GE-2000"}),
         :ok <-
           if(Vws.CEC.Library.enabled?(ws), do: :ok, else: {:error, "NO PROGRAM LIBRARY"}),
         {:ok, _entries} <- read_directory(ctx),
         {:ok, result} <- Vws.CEC.Library.compare(ws) do
      wanted = Keyword.get(opts, :read_back, false)

      rows =
        for row <- result.programs do
          read_back? = wanted == true or (is_list(wanted) and row.name in wanted)

          # read back what the directory cannot tell: versions sharing size and CRC, a line
          # that could not be read (and, when asked, every program the directory calls the same)
          case row.on_machine do
            on
            when on == :unreadable or (is_tuple(on) and elem(on, 0) == :ambiguous) or
                   (is_tuple(on) and elem(on, 0) == :same and read_back?) ->
              case read_back(ctx, row.name, row.versions) do
                {:same, n} ->
                  %{row | on_machine: {:same, n}} |> Map.put(:read_back, :same)

                :differs ->
                  %{row | on_machine: :differs} |> Map.put(:read_back, :differs)

                {:error, reason} ->
                  Map.put(row, :read_back, {:error, reason})
              end

            _ ->
              row
          end
        end

      {:ok, %{result | programs: rows}}
    else
      {:error, :bad_directory} -> {:error, "BAD DIRECTORY FROM GE-2000"}
      error -> error
    end
  end

  @doc """
  Reads the GE-2000's status report (`RNL`) through `link` and writes the `MONARCH` device status
  (location 8) of workstation `ws`: `{:ok, %{state, program, alarm}}`, or `{:error, reason}` in
  the words of an `ERROR` status. Options: `:check`, `:request_timeout` (as the partition's).
  """
  @spec refresh_status(Mailbox.workstation(), DNC.link(), keyword) ::
          {:ok, Report.status()} | {:error, String.t()}
  def refresh_status(ws, link, options \\ []) do
    status_report(%{workstation: ws, link: link, options: options})
  end

  @doc """
  Writes a status report: the `MONARCH` device status (location 8), `ACTIVE` or `IDLE`, and the
  whole report (program, alarm) for the views and the MTConnect agent. With `asked_at` (the
  monotonic ms at which the report was asked for), nothing is written when location 8 was written
  since (`Mailbox.put_device_unless_newer/4`): `:newer`. A drip feed's blocks say ACTIVE as they
  reach the machine (`Vws.Partitions.Monarch.Monitor`), and a report answered an instant before
  the first block, handed back after it, once made MONARCH `IDLE` while the program ran.
  """
  @spec put_status(Mailbox.workstation(), Report.status(), integer | nil) :: :ok | :newer
  def put_status(ws, report, asked_at \\ nil) do
    word = if report.state == :active, do: "ACTIVE", else: "IDLE"

    written =
      if asked_at,
        do: Mailbox.put_device_unless_newer(ws, @monarch_location, word, asked_at),
        else: Mailbox.put_device(ws, @monarch_location, word)

    if written == :ok, do: Mailbox.put_readings(ws, :monarch, report)
    written
  end

  @doc """
  A program the operator sent from the machine (auto-receive, ours: docs/dnc-drip-feed.md): the
  GE-2000 bid and sent `SCS`/`SNS` + `name` and the program's text unasked. A whole program
  (ending in its `%` line, no control characters) is handed to `store` — by default
  `store_from_machine/3`, which keeps it in the program library as a version from the machine,
  not released — and counted (`[:vws, :monarch, :program_received]`, `from: :machine`); anything
  else is refused and logged. This is the one place a received program is handed over. It never
  touches NC_UP: that is what the WC's `UPLOAD_GE` brought, and only that. Recorded in the
  transfer history (`Vws.Partitions.Monarch.Transfers.received/5`; `blocks`, the text blocks it
  came in), whatever became of it.
  """
  @spec received_program(
          Mailbox.workstation(),
          String.t(),
          binary,
          (term, String.t(), [binary] ->
             :ok | {:error, term}),
          non_neg_integer
        ) ::
          :ok | {:error, String.t()}
  def received_program(ws, name, text, store \\ &store_from_machine/3, blocks \\ 0) do
    lines = Program.from_text(text)

    result =
      cond do
        Program.check_size(text) != :ok -> Program.check_size(text)
        not Program.complete?(text) -> {:error, "PROGRAM INCOMPLETE"}
        Program.check_lines(lines) != :ok -> {:error, "PROGRAM HOLDS A CONTROL CHARACTER"}
        true -> store.(ws, name, lines)
      end

    Vws.Telemetry.execute([:vws, :monarch, :program_received], %{bytes: byte_size(text)}, %{
      workstation: ws,
      program: name,
      from: :machine,
      result: if(result == :ok, do: :ok, else: :error)
    })

    result =
      case result do
        :ok -> :ok
        {:error, reason} when is_binary(reason) -> {:error, reason}
        {:error, reason} -> {:error, "NOT STORED #{Vws.Codecs.WC.Words.of(reason)}"}
      end

    Transfers.received(ws, name, text, blocks, result)
    result
  end

  @doc """
  Keeps a program received from the machine in the workstation's program library: a new
  version, source `"from the machine"` — not released, so `DOWNLOAD_GE(nnnnnn.PRO)` never sends
  it; only a `DOWNLOAD_GE(nnnnnn.PRO/v)` naming it does, or a release (`mix vws.library release`,
  `Vws.CEC.Library.release/4`). When a version already holds exactly these bytes (the same
  SHA-256 digest) nothing new is stored. NC_UP is left alone: it holds only what the WC's
  `UPLOAD_GE` asked for. Without a library the program is refused (`NO PROGRAM LIBRARY`, logged
  by the monitor).
  """
  @spec store_from_machine(Mailbox.workstation(), String.t(), [binary]) :: :ok | {:error, term}
  def store_from_machine(ws, name, lines) do
    require Logger

    if Vws.CEC.Library.enabled?(ws) do
      case Vws.CEC.Library.store(ws, name, Program.to_text(lines),
             source: "from the machine",
             only_if_new: true
           ) do
        {:ok, v} ->
          Logger.info(
            "MONARCH: program #{name} received from the machine (#{length(lines)} lines): " <>
              "library version #{v.version} (#{Vws.CEC.Library.release_text(v)})"
          )

          :ok

        {:error, reason} ->
          {:error, "LIBRARY #{words(reason)}"}
      end
    else
      {:error, "NO PROGRAM LIBRARY"}
    end
  end

  # The NC file as a program to send: its file name (from its program number) and its text.
  defp nc_file_program(ws) do
    lines = Mailbox.nc_file(ws)

    with :ok <- if(lines == [], do: {:error, "NO NC FILE"}, else: :ok),
         {:ok, file} <- program_file(lines),
         :ok <- sendable(lines),
         text = Program.to_text(lines),
         :ok <- if(Program.complete?(text), do: :ok, else: {:error, "NC FILE HAS NO CLOSING %"}),
         do: {:ok, file, text}
  end

  # One S (or E) transmission of the program's text blocks, then the status report: no alarm.
  defp send_program(ctx, operation, name, text, failed) do
    with {:ok, max_text} <- max_text(ctx),
         {:ok, _} <- request(ctx, :send, operation, name, Frame.split_text(text, max_text)),
         {:ok, _report} <- verify(ctx, failed, fn _ -> true end),
         do: :ok
  end

  # RNL → the report; every report read refreshes the MONARCH device status, unless location 8
  # was written since it was asked for (put_status/3).
  defp status_report(ctx) do
    asked_at = System.monotonic_time(:millisecond)

    with {:ok, blocks} <- request(ctx, :receive, :status, "", []) do
      case Report.parse_status(IO.iodata_to_binary(blocks)) do
        {:ok, report} ->
          put_status(ctx.workstation, report, asked_at)
          {:ok, report}

        {:error, _} ->
          {:error, "BAD STATUS REPORT FROM GE-2000"}
      end
    end
  end

  defp request(ctx, direction, operation, text, blocks) do
    command = %Command{
      direction: direction,
      check: Keyword.get(ctx.options, :check, :crc),
      operation: operation,
      text: text
    }

    timeout = Keyword.get(ctx.options, :request_timeout, :infinity)

    Transfers.carried(ctx, command, blocks, fn ->
      send_request(ctx, command, blocks, timeout, @request_tries)
    end)
  end

  # A transmission the line broke off left nothing behind (a DNC receiver never keeps part of
  # one), so a request that has the same effect once or twice — reading a report, a table or a
  # program, storing a whole program (it replaces the file), selecting one — is made again, at
  # most twice more. A delete is not (the second would find no file), nor a request refused
  # for good (a link down, the peer busy, a bad text).
  defp send_request(ctx, command, blocks, timeout, tries) do
    case port(ctx).request(ctx.link, command, blocks, timeout) do
      {:ok, blocks} ->
        {:ok, blocks}

      # a port that answers in words (Vws.Links.RS232: what a plain RS-232 control cannot do)
      {:error, words} when is_binary(words) ->
        {:error, words}

      {:error, %LinkError{reason: reason}}
      when tries > 1 and reason in @broken_off and command.operation not in @not_again ->
        Vws.Telemetry.execute([:vws, :monarch, :request_again], %{count: 1}, %{
          workstation: ctx.workstation,
          operation: command.operation,
          reason: reason
        })

        Transfers.again()
        send_request(ctx, command, blocks, timeout, tries - 1)

      {:error, %LinkError{} = e} ->
        {:error, LinkError.status_text(e)}
    end
  end

  # The port's profile, and the link module that serves it (Vws.Links.ProgramPort): the
  # GE-2000's DNC Level 2 unless the workstation's devices: say otherwise. A plain RS-232
  # control has no status report nor directory to verify with: its link reads a download back.
  defp profile(ctx), do: Keyword.get(ctx.options, :profile, :ge2000_level2)
  defp port(ctx), do: Vws.Links.ProgramPort.Profile.link_module(profile(ctx))
  defp verify?(ctx), do: Keyword.get(ctx.options, :verify, profile(ctx) == :ge2000_level2)

  defp max_text(ctx) do
    {:ok, port(ctx).max_text(ctx.link)}
  catch
    :exit, _ -> {:error, LinkError.status_text(%LinkError{reason: :link_down})}
  end

  defp program_file(lines) do
    case Program.file_name(lines) do
      {:ok, file} -> {:ok, file}
      {:error, :no_program_number} -> {:error, "NC FILE HAS NO PROGRAM NUMBER"}
      {:error, :bad_program_number} -> {:error, "NC FILE PROGRAM NUMBER OVER 6 DIGITS"}
    end
  end

  defp sendable(lines) do
    case Program.check_lines(lines) do
      :ok -> :ok
      {:error, n} -> {:error, "NC FILE LINE #{n} HOLDS A CONTROL CHARACTER"}
    end
  end

  defp uploadable(lines, file) do
    case Program.check_lines(lines) do
      :ok -> :ok
      {:error, n} -> {:error, "#{file} LINE #{n} HOLDS A CONTROL CHARACTER"}
    end
  end

  defp offsets(blocks) do
    case Report.parse_offsets(IO.iodata_to_binary(blocks)) do
      {:ok, table} -> {:ok, table}
      {:error, _} -> {:error, "BAD TOOL-OFFSET TABLE FROM GE-2000"}
    end
  end

  defp select_offsets(table, wanted) do
    case Enum.reject(wanted, &Map.has_key?(table, &1)) do
      [] -> {:ok, Enum.map(wanted, &Map.fetch!(table, &1))}
      [missing | _] -> {:error, "TOOL-OFFSET LINE #{missing} NOT IN TABLE"}
    end
  end

  defp reason_text(reason) when is_binary(reason), do: String.upcase(reason)
  defp reason_text(reason), do: Vws.Codecs.WC.Words.of(reason)

  defp now, do: System.monotonic_time(:millisecond)
end
