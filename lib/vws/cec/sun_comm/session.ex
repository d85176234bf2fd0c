defmodule Vws.CEC.SunComm.Session do
  @moduledoc """
  SUN_COMM's Parser and its two NC transfers as data (PROTOCOLS.md §1; the protocol is told in
  `Vws.CEC.SunComm`): a struct and pure functions, in the shape of `Vws.Links.DDCMP.Protocol`.
  No process, no I/O, no timers, no logging. The link — listening, accepting, a takeover, a tty
  reopened, the bytes cut into lines — is the process's (`Vws.CEC.SunComm.Server`).

  Every function that moves the session returns `{session, replies, effects}`:

    * `replies` — `Vws.Codecs.WC.Reply.t()` terms to send to the WC, in order, before the effects;
    * `effects`, in order, for the process around it to carry out:
      * `{:remember_string, sequence, line}` — the last accepted string (rule 4), for a restart;
      * `{:status, set, number, status}` — a command that does not run gets `status` (`set` a
        partition, or `{:unknown, letter}` for a set letter the CEC does not know);
      * `{:finish, number, status}` — the Monarch command `number` (a transfer) ended;
      * `{:timer, :no_line | :no_answer, milliseconds}` — (re)arm the transfer's timer; it lasts
        as long as the mode (`mode/1`), and when it expires call `handle_timeout/3` with its name;
      * `{:log, level, message}` and `{:telemetry, event, measurements, metadata}` (the caller
        adds the workstation);
    * the last effect may be a request whose answer the session needs before it goes on; the
      caller carries it out and gives its answer to `handle_result/3` at once, before anything
      else reaches the session:
      * `{:journal, record}` — make `record` durable: `:ok | {:error, reason}`;
      * `{:dispatch, set, number, text}` — hand the command to its partition (CMD_IN and the
        partition's event): `:ok | {:busy, previous} | {:error, words}`;
      * `{:claim, :monarch, number, text}` — the same for a transfer, which SUN_COMM itself carries
        out (CMD_IN, no event);
      * `{:read_status, name}` — the answer text of status command `name`;
      * `{:read_nc_up}` — NC_UP's lines;
      * `{:store_program, lines}` — store a downloaded program durably: `:ok | {:error, reason}`.

  `ctx` is `%{now: monotonic_ms}`.

      iex> alias Vws.CEC.SunComm.Session
      iex> s = Session.new()
      iex> string = %Vws.Codecs.WC.CommandString{sequence: 13, commands: [Vws.Codecs.WC.Command.new("S", 13, "ROBOT_CMD")]}
      iex> line = string |> Vws.Codecs.WC.CommandString.encode() |> IO.iodata_to_binary() |> String.trim_trailing()
      iex> {s, [], [_telemetry, {:read_status, "ROBOT_CMD"}]} = Session.handle_line(s, line, %{now: 0})
      iex> {_s, replies, []} = Session.handle_result(s, "0000NONE", %{now: 0})
      iex> replies
      [{:status, 13, "0000NONE"}]
  """

  alias Vws.Codecs.WC.{Command, CommandString, ProgramCRC, Reply}

  # what a command of the first string after a damaged journal answers (see journaled/4)
  @last_string_unknown "NOT RUN LAST STRING UNKNOWN AFTER JOURNAL DAMAGE SEND AGAIN"

  @counters [
    :strings,
    :naks,
    :retransmissions,
    :rules_broken,
    :status_answers,
    :lines_in,
    :lines_out,
    :lines_again,
    :operator_commands
  ]

  defstruct bcc: :sum,
            max_program_bytes: 4 * 1024 * 1024,
            download_timeout: 30_000,
            upload_timeout: 5_000,
            upload_retries: 5,
            # the last accepted string {sequence, line} (rule 4)
            last_string: {nil, nil},
            # the download or upload under way, else nil
            transfer: nil,
            # the closing line of the last download and its answer: a resend of it after the
            # transfer ended (its answer was damaged) is answered again
            last_closing: nil,
            # what the session does with the answer to its last request (handle_result/3)
            awaiting: nil,
            counters: Map.new(@counters, &{&1, 0}),
            # what one call produces, newest first; emptied when the call returns
            replies: [],
            effects: []

  @type t :: %__MODULE__{}
  @type ctx :: %{now: integer}
  @type request ::
          {:journal, tuple}
          | {:dispatch | :claim, atom, 0..9999, String.t()}
          | {:read_status, String.t()}
          | {:read_nc_up}
          | {:store_program, [binary]}
  @type effect ::
          {:remember_string, 0..9999, binary}
          | {:status, atom | {:unknown, String.t()}, 0..9999, term}
          | {:finish, 0..9999, :done | {:error, String.t()}}
          | {:timer, :no_line | :no_answer, pos_integer}
          | {:log, Logger.level(), String.t()}
          | {:telemetry, [atom], map, map}
          | request
  @type result :: {t, [Reply.t()], [effect]}

  @doc """
  A session in command mode. Options: `:bcc`, `:max_program_bytes`, `:download_timeout`,
  `:upload_timeout`, `:upload_retries` (see `Vws.CEC.SunComm`) and `:last_string`, the last
  accepted string `{sequence, line}` a restarted SUN_COMM finds in the mailboxes (or
  `{:unknown, nil}` after a damaged journal: the first command string then runs nothing).
  """
  @spec new(keyword) :: t
  def new(opts \\ []) do
    struct!(
      __MODULE__,
      Keyword.take(opts, [
        :bcc,
        :max_program_bytes,
        :download_timeout,
        :upload_timeout,
        :upload_retries,
        :last_string
      ])
    )
  end

  @doc "The mode: `:command`, `:download` or `:upload`."
  @spec mode(t) :: :command | :download | :upload
  def mode(%__MODULE__{transfer: nil}), do: :command
  def mode(%__MODULE__{transfer: %{kind: kind}}), do: kind

  @doc "The counters."
  @spec counters(t) :: %{atom => non_neg_integer}
  def counters(%__MODULE__{counters: counters}), do: counters

  @doc """
  The transfer under way for `Vws.CEC.SunComm.info/1`: its kind, command number, lines and
  bytes so far, the totals when known (an upload's), its start (monotonic ms); nil in command
  mode.
  """
  @spec transfer_info(t) :: map | nil
  def transfer_info(%__MODULE__{transfer: nil}), do: nil

  def transfer_info(%__MODULE__{transfer: %{kind: :download} = d}),
    do: %{
      kind: "DOWNLOAD_HP",
      number: d.number,
      lines: d.count,
      bytes: d.bytes,
      total_lines: nil,
      total_bytes: nil,
      started_ms: d.started
    }

  def transfer_info(%__MODULE__{transfer: %{kind: :upload} = u}),
    do: %{
      kind: "UPLOAD_SUN",
      number: u.number,
      lines: u.sent,
      bytes: u.bytes,
      total_lines: u.total,
      total_bytes: u.total_bytes,
      started_ms: u.started
    }

  @doc "`{:download | :upload, number, lines so far}` during a transfer, else `:command`."
  @spec mode_name(t) :: :command | {:download | :upload, 0..9999, non_neg_integer}
  def mode_name(%__MODULE__{transfer: nil}), do: :command
  def mode_name(%__MODULE__{transfer: %{kind: :download} = d}), do: {:download, d.number, d.count}
  def mode_name(%__MODULE__{transfer: %{kind: :upload} = u}), do: {:upload, u.number, u.sent}

  ## Lines in

  @doc """
  One line from the WC (without its CR LF), or `{:error, %Vws.Codecs.WC.Error{}}` for one the
  line decoder refused (too long): answered `E`.
  """
  @spec handle_line(t, binary | {:error, Exception.t()}, ctx) :: result
  def handle_line(%__MODULE__{awaiting: nil} = s, {:error, error}, _ctx),
    do: s |> reject(error.reason) |> done()

  def handle_line(%__MODULE__{awaiting: nil, transfer: nil} = s, line, ctx),
    do: s |> command_line(line, ctx) |> done()

  def handle_line(%__MODULE__{awaiting: nil, transfer: %{kind: kind}} = s, line, ctx) do
    case string_during_transfer(line, s) do
      {:ok, cs} -> command_string_in_transfer(s, cs, line, kind, ctx)
      _no_string when kind == :download -> download_line(s, line)
      _no_string -> upload_answer(s, line)
    end
    |> done()
  end

  @doc """
  The end of a line never came (its CR LF was lost or damaged on the line): answered `E`,
  except during an upload, where the WC only answers and a missing answer is resent for.
  """
  @spec unfinished_line(t) :: result
  def unfinished_line(%__MODULE__{awaiting: nil, transfer: %{kind: :upload}} = s), do: done(s)
  def unfinished_line(%__MODULE__{awaiting: nil} = s), do: s |> reject(:unfinished_line) |> done()

  @doc "A timer of `{:timer, name, ms}` expired; a stale one (another mode) does nothing."
  @spec handle_timeout(t, :no_line | :no_answer, ctx) :: result
  def handle_timeout(
        %__MODULE__{awaiting: nil, transfer: %{kind: :download} = d} = s,
        :no_line,
        _
      ) do
    why = "DOWNLOAD STALLED AFTER #{d.count} LINES"
    s |> end_transfer(d.number, {:error, why}) |> done()
  end

  def handle_timeout(%__MODULE__{awaiting: nil, transfer: %{kind: :upload}} = s, :no_answer, _),
    do: s |> resend_upload_line() |> done()

  def handle_timeout(%__MODULE__{awaiting: nil} = s, _stale, _ctx), do: done(s)

  @doc """
  The WC's link ended or was taken over by another connection (`why`, upper-case words such as
  `"WC LINK LOST"`): a transfer under way ends `ERROR`.
  """
  @spec link_lost(t, String.t()) :: result
  def link_lost(%__MODULE__{awaiting: nil} = s, why), do: s |> abort_transfer(why) |> done()

  @doc """
  A command of this node's operator, not from the WC: the Parser's rules for one command and
  the same dispatch, nothing on the WC link, the WC's last string untouched; transfers are for
  the WC only. Returns `:ok` (dispatched; the status tells the rest) or `{:error, words}`, and
  the session's result.
  """
  @spec local_command(t, String.t(), 0..9999, String.t(), ctx) ::
          {:ok | {:error, String.t()}, result}
  def local_command(%__MODULE__{awaiting: nil} = s, letter, number, text, ctx) do
    command = %{set: Command.set_for_letter(letter), number: number, text: text}

    cond do
      command.set not in Vws.CEC.Mailbox.partitions() ->
        {{:error, "UNKNOWN COMMAND SET #{letter}"}, done(s)}

      transfer_of(command) != nil ->
        {{:error, "TRANSFER WITH THE WC ONLY"}, done(s)}

      true ->
        s =
          s
          |> log(:info, "operator command #{letter}#{Command.pad4(number)} #{text}")
          |> bump(:operator_commands)
          |> dispatch_next([command], nil, ctx)

        {:ok, done(s)}
    end
  end

  @doc "The answer to the request that ended the last result (see the moduledoc)."
  @spec handle_result(t, term, ctx) :: result
  def handle_result(%__MODULE__{awaiting: next} = s, answer, ctx) when next != nil,
    do: %{s | awaiting: nil} |> resume(next, answer, ctx) |> done()

  ## Command strings

  defp command_line(s, "", _ctx), do: reject(s, :empty_line)

  defp command_line(%{last_closing: {line, answer}} = s, line, _ctx) do
    s
    |> log(:info, "the closing line of the last download again: answered again")
    |> reply(answer)
    |> bump(:lines_again)
  end

  defp command_line(s, line, ctx) do
    case CommandString.decode(line, bcc: s.bcc) do
      {:error, error} -> reject(%{s | last_closing: nil}, error.reason)
      {:ok, cs} -> string_received(s, cs, line, ctx)
    end
  end

  # A decoded string, in command mode (or just back in it from a transfer the string ended).
  defp string_received(s, cs, line, ctx) do
    %{s | last_closing: nil}
    |> bump(:strings)
    |> telemetry(:string_received, %{bytes: byte_size(line)}, %{
      sequence: cs.sequence,
      commands: length(cs.commands)
    })
    |> accept_string(cs, line, ctx)
  end

  # The Parser's rules. Status strings are not remembered for rule 4: answering one twice is
  # harmless, and a status poll between a lost acknowledgement and its resend must not hide the
  # resend. Anything else is made durable before it is acknowledged.
  defp accept_string(s, cs, line, _ctx) do
    cond do
      status_string?(cs) ->
        [status] = cs.commands
        request(s, {:read_status, status.text}, {:status_answer, status.number})

      s.last_string == {cs.sequence, line} ->
        acknowledge_again(s, cs, "is a retransmission: acknowledged again, nothing executed")

      true ->
        commands =
          for %{set: set, number: n} <- cs.commands,
              set in Vws.CEC.Mailbox.partitions(),
              do: {set, n}

        request(s, {:journal, {:string, cs.sequence, line, commands}}, {:journaled, cs, line})
    end
  end

  # rule 4: the last accepted string again (its acknowledgement was lost)
  defp acknowledge_again(s, cs, what) do
    s
    |> log(:info, "string #{cs.sequence} #{what}")
    |> telemetry(:retransmission, %{count: 1}, %{sequence: cs.sequence})
    |> bump(:retransmissions)
    |> reply({:ack, cs.sequence})
  end

  defp status_string?(%{commands: [%{set: :status}]}), do: true
  defp status_string?(_), do: false

  defp broken_rule(cs) do
    letters = Enum.map(cs.commands, & &1.letter)

    cond do
      unknown = Enum.find(cs.commands, &match?({:unknown, _}, &1.set)) ->
        "UNKNOWN COMMAND SET #{unknown.letter}"

      Enum.any?(cs.commands, &(&1.set == :status)) ->
        "RULE 2 STATUS COMMAND NOT ALONE"

      dup = Enum.find(letters, &(Enum.count(letters, fn l -> l == &1 end) > 1)) ->
        "RULE 1 SET #{dup} REPEATED"

      true ->
        nil
    end
  end

  # A journaled string: acknowledged, then either nothing in it runs (a rule broken: each
  # command answers the rule on its next status query) or its commands go to their partitions.
  #
  # After a damaged journal the last string is unknown (`{:unknown, nil}`): the first string
  # then may be the lost one sent again, which rule 4 cannot recognise, and its commands may
  # already have run (a robot move is physical). It is acknowledged and nothing in it runs; each
  # command answers so on its next status query, and the WC sends them again under a new
  # sequence number. Only that first string: the next ones are known again.
  defp journaled(s, cs, line, ctx) do
    last_unknown? = match?({:unknown, _}, s.last_string)

    s =
      s
      |> effect({:remember_string, cs.sequence, line})
      |> Map.put(:last_string, {cs.sequence, line})
      |> reply({:ack, cs.sequence})

    case broken_rule(cs) do
      nil when last_unknown? ->
        s
        |> log(
          :warning,
          "string #{cs.sequence}: the last string was lost with the damaged journal, so this " <>
            "one may be it again: nothing in it runs (#{@last_string_unknown})"
        )
        |> run_nothing(cs, @last_string_unknown)

      nil ->
        dispatch_next(s, cs.commands, nil, ctx)

      broken ->
        s
        |> log(:warning, "string #{cs.sequence} breaks a rule (#{broken}): nothing in it runs")
        |> telemetry(:rule_broken, %{count: 1}, %{sequence: cs.sequence, rule: broken})
        |> bump(:rules_broken)
        |> run_nothing(cs, broken)
    end
  end

  # Each command of an acknowledged string that must not run answers `why` on its next query.
  defp run_nothing(s, cs, why) do
    for %{set: set, number: n} <- cs.commands, set not in [:ack, :status], reduce: s do
      s -> effect(s, {:status, set, n, {:error, why}})
    end
  end

  # The commands of an accepted string, one at a time, then the transfer one of them begins
  # (rule 1: one Monarch command at most, so one transfer at most).
  defp dispatch_next(s, [], transfer, ctx), do: start_transfer(s, transfer, ctx)

  defp dispatch_next(s, [%{set: :ack} = command | rest], transfer, ctx) do
    s
    |> log(:debug, "acknowledgement command #{command.number} #{command.text}")
    |> dispatch_next(rest, transfer, ctx)
  end

  # the two transfers SUN_COMM carries out are claimed (recognised here); every other command
  # is handed to its partition, which parses it
  defp dispatch_next(s, [%{set: set, number: n, text: text} = command | rest], transfer, _ctx) do
    how = if transfer_of(command), do: :claim, else: :dispatch
    request(s, {how, set, n, text}, {:dispatched, command, rest, transfer})
  end

  defp dispatched(s, command, rest, transfer, answer, ctx) do
    %{set: set, number: n} = command

    case answer do
      {:busy, previous} ->
        s
        |> log(:warning, "#{set} command #{n} refused: command #{previous} still in flight")
        |> effect({:status, set, n, {:error, "BUSY #{Command.pad4(previous)}"}})
        |> dispatch_next(rest, transfer, ctx)

      {:error, _not_durable} ->
        # not durable, so not run: its status says so
        dispatch_next(s, rest, transfer, ctx)

      :ok ->
        s
        |> claimed(command)
        |> dispatch_next(rest, transfer_of(command) || transfer, ctx)
    end
  end

  # A transfer's command is reported dispatched as `Vws.CEC.Partition.dispatch/4` reports the
  # others (which it does before their partition hears of them).
  defp claimed(s, %{set: set, number: n, text: text} = command) do
    if transfer_of(command),
      do:
        effect(
          s,
          {:telemetry, [:vws, :partition, :command_dispatched], %{count: 1},
           %{partition: set, command: n, text: text}}
        ),
      else: s
  end

  # The transfer a command begins: the WC names the program's CRC, or not (the seed's form), or
  # names it badly; the program's lines follow in every case, and the check is made at its end.
  defp transfer_of(%{set: :monarch, number: n, text: text}) do
    case Vws.Codecs.Commands.transfer(text) do
      :download_hp -> {:download, n, nil}
      {:download_hp, crc} -> {:download, n, crc}
      {:error, why} -> {:download, n, {:error, why}}
      :upload_sun -> {:upload, n}
      _ -> nil
    end
  end

  defp transfer_of(_command), do: nil

  ## Answers to requests

  defp resume(s, {:status_answer, number}, text, _ctx),
    do: s |> bump(:status_answers) |> reply({:status, number, text})

  defp resume(s, {:journaled, cs, line}, :ok, ctx), do: journaled(s, cs, line, ctx)

  # not durable, so not acknowledged: the WC sends it again
  defp resume(s, {:journaled, _cs, _line}, {:error, _}, _ctx), do: reject(s, :journal_unavailable)

  defp resume(s, {:dispatched, command, rest, transfer}, answer, ctx),
    do: dispatched(s, command, rest, transfer, answer, ctx)

  defp resume(s, {:nc_up, number}, [], _ctx),
    do: end_transfer(%{s | transfer: nil}, number, {:error, "NO UPLOADED PROGRAM"})

  defp resume(s, {:nc_up, number}, lines, ctx) do
    s
    |> log(:info, "UPLOAD_SUN #{number}: sending #{length(lines)} lines to the WC")
    |> Map.put(:transfer, %{
      kind: :upload,
      number: number,
      lines: lines,
      sent: 0,
      retries: 0,
      started: ctx.now,
      total: length(lines),
      bytes: 0,
      total_bytes: Enum.reduce(lines, 0, &(byte_size(&1) + 1 + &2)),
      crc: ProgramCRC.compute(lines)
    })
    |> send_upload_line()
  end

  defp resume(s, {:stored, line, answer, d}, :ok, _ctx) do
    s
    |> reply(answer)
    |> log(:info, "DOWNLOAD_HP #{d.number}: #{d.count} lines stored as the NC file")
    |> end_transfer(d.number, :done)
    |> Map.put(:last_closing, {line, answer})
  end

  defp resume(s, {:stored, _line, _answer, d}, {:error, reason}, _ctx) do
    s
    |> reject(:journal_unavailable)
    |> log(:error, "DOWNLOAD_HP #{d.number}: NC file not stored: #{inspect(reason)}")
    |> end_transfer(d.number, {:error, "NC FILE NOT STORED #{Vws.Codecs.WC.Words.of(reason)}"})
  end

  ## Transfers

  # A download begins at once; an upload reads NC_UP first (`{:nc_up, n}`). Either begins once
  # every command of its string is dispatched.
  defp start_transfer(s, nil, _ctx), do: s

  # `expected`: the program's CRC the WC named, nil (none named) or `{:error, why}` (named
  # badly); `crc` the CRC of the lines stored so far (PROTOCOLS.md §1 "Whole-program check")
  defp start_transfer(s, {:download, number, expected}, ctx) do
    d = %{
      kind: :download,
      number: number,
      expected: expected,
      lines: [],
      count: 0,
      bytes: 0,
      crc: 0,
      started: ctx.now
    }

    s
    |> log(:info, "DOWNLOAD_HP #{number}: reading program lines from the WC")
    |> Map.put(:transfer, d)
    |> download_timer()
  end

  defp start_transfer(s, {:upload, number}, _ctx),
    do: request(s, {:read_nc_up}, {:nc_up, number})

  # the transfer a resent string begins again
  defp again(%{kind: :download} = d), do: {:download, d.number, d.expected}
  defp again(%{kind: :upload} = u), do: {:upload, u.number}

  defp download_timer(s), do: effect(s, {:timer, :no_line, s.download_timeout})

  # An intact command string during a program transfer: the WC is not in the transfer.
  defp string_during_transfer("*" <> _ = line, s), do: CommandString.decode(line, bcc: s.bcc)
  defp string_during_transfer(_line, _s), do: :no

  # The string that began the transfer, again: its acknowledgement was lost and the WC is
  # still waiting for it, so it is acknowledged again and the transfer begins afresh from its
  # first line (the WC sends or takes the program only after the acknowledgement). A status
  # query during an upload is answered and the upload goes on: it runs nothing, and a WC that
  # has taken the closing line asks its command's status while its answer reached us damaged —
  # the closing line goes again and it answers again. Any other string (and a status query
  # during a download, where the WC is the sender): the WC gave the transfer up; it ends
  # ERROR and the string is handled as usual.
  defp command_string_in_transfer(s, cs, line, kind, ctx) do
    cond do
      s.last_string == {cs.sequence, line} ->
        s
        |> acknowledge_again(cs, "again during #{kind}: acknowledged again, transfer restarted")
        |> Map.put(:transfer, nil)
        |> start_transfer(again(s.transfer), ctx)

      kind == :upload and status_string?(cs) ->
        accept_string(s, cs, line, ctx)

      true ->
        s
        |> log(:warning, "string #{cs.sequence} during #{kind}: the WC left the transfer")
        |> abort_transfer("COMMAND STRING FROM THE WC")
        |> string_received(cs, line, ctx)
    end
  end

  ## NC download (WC → CEC)

  defp download_line(%{transfer: d} = s, line) do
    next = rem(d.count + 1, 10_000)
    last = if d.count > 0, do: rem(d.count, 10_000)

    case Reply.decode_line(line, bcc: s.bcc) do
      {:error, error} ->
        s |> reject(error.reason) |> download_timer()

      {:ok, {:line, ^next, text}} ->
        store_download_line(s, line, text, d)

      {:ok, {:line, ^last, _text}} ->
        # the WC did not take our answer for its line: the same line again, stored once
        s |> reply({:line_ack, last}) |> bump(:lines_again) |> download_timer()

      {:ok, {:line, n, _text}} ->
        s
        |> log(:warning, "DOWNLOAD_HP #{d.number}: line #{n} came when #{next} was due")
        |> reject(:line_out_of_order)
        |> end_transfer(d.number, {:error, "PROGRAM LINE OUT OF ORDER"})
    end
  end

  defp store_download_line(s, line, text, d) do
    s =
      s
      |> bump(:lines_in)
      |> telemetry(:nc_line, %{bytes: byte_size(text)}, %{direction: :in})

    d = %{
      d
      | lines: [text | d.lines],
        count: d.count + 1,
        bytes: d.bytes + byte_size(text) + 1,
        crc: ProgramCRC.add_line(d.crc, text)
    }

    cond do
      d.bytes > s.max_program_bytes ->
        why = "NC PROGRAM LARGER THAN #{s.max_program_bytes} BYTES"
        s |> reject(:program_too_large) |> end_transfer(d.number, {:error, why})

      String.trim(text) == "%" and d.count > 1 ->
        close_download(%{s | transfer: d}, line, d)

      true ->
        %{s | transfer: d} |> reply({:line_ack, rem(d.count, 10_000)}) |> download_timer()
    end
  end

  # The closing `%`: answered `A` + the number of lines + `/` + the CRC of what came, whatever
  # follows, so the WC can compare the whole program too (and a resend of the closing line
  # gets the same answer). The program is stored only if it is the one the WC named (when it
  # named one) and not larger than a program may be (PROTOCOLS.md §2 "Program size limit");
  # otherwise the command ends ERROR and the NC file and the library keep what they had.
  defp close_download(s, line, d) do
    answer = {:line_ack, rem(d.count, 10_000), d.crc}

    # d.bytes: the size of the program's text, every line with its LF
    refused =
      with :ok <- program_crc(d.expected, d.crc),
           do: Vws.Links.DNC.Program.check_size(d.bytes)

    case refused do
      :ok ->
        request(s, {:store_program, Enum.reverse(d.lines)}, {:stored, line, answer, d})

      {:error, why} ->
        s
        |> log(
          :warning,
          "DOWNLOAD_HP #{d.number}: #{d.count} lines received, not stored: #{why}; " <>
            "the NC file is kept as it was"
        )
        |> telemetry(:string_rejected, %{bytes: 0}, %{reason: refusal(why)})
        |> reply(answer)
        |> end_transfer(d.number, {:error, why})
        |> Map.put(:last_closing, {line, answer})
    end
  end

  defp refusal("PROGRAM TOO LARGE" <> _), do: :program_too_large
  defp refusal(_why), do: :program_crc

  defp program_crc(nil, _crc), do: :ok
  defp program_crc({:error, why}, _crc), do: {:error, why}
  defp program_crc(crc, crc), do: :ok

  defp program_crc(expected, crc),
    do: {:error, "PROGRAM CRC #{ProgramCRC.format(crc)} EXPECTED #{ProgramCRC.format(expected)}"}

  ## NC upload (CEC → WC)

  defp send_upload_line(%{transfer: %{lines: [line | rest]} = u} = s) do
    s
    |> telemetry(:nc_line, %{bytes: byte_size(line)}, %{direction: :out})
    |> reply({:line, rem(u.sent + 1, 10_000), upload_text(line, rest, u)})
    |> bump(:lines_out)
    |> effect({:timer, :no_answer, s.upload_timeout})
  end

  defp upload_answer(%{transfer: u} = s, line) do
    this = rem(u.sent + 1, 10_000)
    previous = if u.sent > 0, do: rem(u.sent, 10_000)

    case Reply.decode(line, bcc: s.bcc) do
      {:ok, {:line_ack, ^this}} ->
        case u.lines do
          [_last] ->
            s
            |> log(:info, "UPLOAD_SUN #{u.number}: #{u.sent + 1} lines sent")
            |> end_transfer(u.number, :done)

          [sent | rest] ->
            u = %{
              u
              | lines: rest,
                sent: u.sent + 1,
                retries: 0,
                bytes: u.bytes + byte_size(sent) + 1
            }

            send_upload_line(%{s | transfer: u})
        end

      {:ok, {:line_ack, ^previous}} ->
        # a late second answer to the line before (sent again after a silence): nothing new
        s

      {:ok, :nak} ->
        resend_upload_line(s)

      _ ->
        # a damaged answer, or one naming another line: this line is not known to be stored
        s
        |> log(
          :warning,
          "during UPLOAD_SUN the WC sent #{inspect(line)}; expected A#{Command.pad4(this)}"
        )
        |> resend_upload_line()
    end
  end

  # The closing `%` carries the program's CRC as `%/cccc` (PROTOCOLS.md §1 "Whole-program
  # check"): the `%` stays first, so a WC that looks only for `%` still ends there.
  defp upload_text(line, [], u) do
    if String.trim(line) == "%" and u.total > 1,
      do: ProgramCRC.closing_line(line, u.crc),
      else: line
  end

  defp upload_text(line, _rest, _u), do: line

  defp resend_upload_line(%{transfer: u} = s) do
    if u.retries >= s.upload_retries do
      why = "UPLOAD LINE #{u.sent + 1} NOT ACKNOWLEDGED AFTER #{u.retries + 1} TRIES"
      end_transfer(s, u.number, {:error, why})
    else
      send_upload_line(%{s | transfer: %{u | retries: u.retries + 1}})
    end
  end

  ## Transfer endings

  defp abort_transfer(%{transfer: nil} = s, _why), do: s

  defp abort_transfer(%{transfer: %{kind: :download} = d} = s, why),
    do: end_transfer(s, d.number, {:error, "#{why} DURING DOWNLOAD AFTER #{d.count} LINES"})

  defp abort_transfer(%{transfer: %{kind: :upload} = u} = s, why),
    do: end_transfer(s, u.number, {:error, "#{why} DURING UPLOAD AFTER #{u.sent} LINES"})

  defp end_transfer(s, number, status),
    do: %{effect(s, {:finish, number, status}) | transfer: nil}

  ## Building a result

  defp reject(s, reason) do
    s
    |> telemetry(:string_rejected, %{bytes: 0}, %{reason: reason})
    |> reply(:nak)
    |> bump(:naks)
  end

  defp reply(s, reply), do: %{s | replies: [reply | s.replies]}
  defp effect(s, effect), do: %{s | effects: [effect | s.effects]}
  defp log(s, level, message), do: effect(s, {:log, level, message})

  defp telemetry(s, event, measurements, metadata),
    do: effect(s, {:telemetry, [:vws, :sun_comm, event], measurements, metadata})

  defp bump(s, key), do: %{s | counters: Map.update!(s.counters, key, &(&1 + 1))}

  # a request ends the result: nothing follows it until its answer came (handle_result/3)
  defp request(s, request, next), do: %{effect(s, request) | awaiting: next}

  defp done(%__MODULE__{} = s) do
    {%{s | replies: [], effects: []}, Enum.reverse(s.replies), Enum.reverse(s.effects)}
  end
end
