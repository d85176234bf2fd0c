defmodule Vws.Peers.WC.Client do
  @moduledoc """
  A workstation controller (WC) for the CEC: the Sun's side of the WC link (seed §2.3.1–2.3.7,
  PROTOCOLS.md §1), over any `Vws.Links.Transport` endpoint.

  It numbers what it sends as the seed's WC did: every string gets the next four-digit
  sequence number, every command the next number of its own set (R, M, F, H, G, V, and S for
  status queries), so a session reads like seed Table 1:

      {:ok, wc} = Vws.Peers.WC.Client.connect("tcp://127.0.0.1:7070", sequence: 54,
                                        numbers: %{"R" => 9, "G" => 4, "S" => 39})
      {:ok, [{"R", 9}, {"G", 4}]} =
        Vws.Peers.WC.Client.send_commands(wc, [{"R", "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"}, {"G", "OPEN"}])
      # sent *0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*241, answered 05A0054111
      :done = Vws.Peers.WC.Client.await_command(wc, "R", 9, 60_000)
      # sent *0055*S0039ROBOT_CMD*032 (again, while the answer is not 0009…), answered 13S00390009DONE114

  ## The link

  A string answered `E` (or with a damaged reply, or not at all within `:reply_timeout`) is sent
  again, byte for byte, at most `:max_resends` times; SUN_COMM recognises a repeated string
  whose acknowledgement was lost and does not run it twice (PROTOCOLS.md §1 rule 4). One request
  is on the link at a time; concurrent callers wait their turn. If the link closes, the next
  request opens it again.

  ## The polling rule (seed §2.3.7)

  `await_command/5` asks the command's status (`ROBOT_CMD`, …) and repeats the question, every
  `:poll_interval` ms, until the command's number appears; then `DONE` is success and anything
  else (`ERROR <reason>`) is returned as the error, with the CEC's reason word for word. A
  command still `EXECUTING` is polled on until the timeout.

  ## NC programs

  `download_program/2` sends `M…DOWNLOAD_HP(cccc)`, naming the program's CRC-16/ARC
  (`Vws.Codecs.WC.ProgramCRC`, PROTOCOLS.md §1 "Whole-program check"), and then the program, one
  numbered line + BCC at a time (`nnnn` + text + BBB, PROTOCOLS.md §1). Only `A` + that number + a
  good BCC counts as stored; `E`, a damaged answer, another number or silence sends the same line
  again (at most `:max_resends` times) — the CEC recognises the resend of a line it stored by its
  number and does not store it twice. The closing `%` is answered `A` + the number of lines +
  `/` + the CRC of what the CEC took: another CRC than the program's fails the request
  (`:program_crc`; the CEC, which was told the CRC, keeps its old NC file and ends the command
  `ERROR PROGRAM CRC …`). `upload_program/1` sends `M…UPLOAD_SUN` and receives NC_UP the same
  way, answering `A` + the line's number, or `E` to a damaged line, and answering a resend of the
  line just stored again without keeping it twice; the closing line `%/cccc` carries the
  program's CRC, and a program received with another CRC fails the request (`:program_crc`).
  The 8-bit-sum BCC of each line lets about one two-bit error in 27 through; the CRC sees it.
  A transfer that breaks off cannot be resumed on the wire, so the client closes and reopens
  the link: SUN_COMM then ends the Monarch command `ERROR`, as it must.

  ## The event log

  Every line sent and received is recorded with its time and meaning as a
  `Vws.Peers.WC.Client.Event`; `subscribe/2` delivers them as `{:wc_client, client, event}`, `log/1`
  returns the most recent ones, and `note/2` adds the caller's own remarks in order.

  ## Options of `connect/2`

    * `:bcc` — `:sum` (default) or `:xor`, as SUN_COMM is configured
    * `:sequence` — the first sequence number (default 1); `:numbers` — the first command number
      per set letter, e.g. `%{"R" => 9}` (default 1 for every set)
    * `:max_resends` — resends of one string or program line (default 3)
    * `:reply_timeout` — ms to wait for the reply to a string (default 5 000)
    * `:line_timeout` — ms to wait for an NC program line or its answer (default 5 000)
    * `:connect_timeout` — ms to keep trying to connect (default 5 000; SUN_COMM opens its
      link only after OK_TO_PROCEED)
    * `:subscribe` — a pid to subscribe at once
  """

  alias Vws.Peers.WC.ClientError
  alias Vws.Codecs.WC.Command
  alias Vws.Peers.WC.Client.Connection

  @type client :: pid
  @type letter :: String.t()

  @command_status_names %{
    "R" => "ROBOT_CMD",
    "M" => "MONARCH_CMD",
    "G" => "GRIPPER_CMD",
    "F" => "FIXTURE_CMD",
    "V" => "VACUUM_CMD",
    "H" => "HYDRAULIC_CMD"
  }

  # SUN_COMM takes lines of at most 1024 bytes; a program line carries three BCC digits too.
  @max_program_line 1021

  @doc """
  Connects to SUN_COMM at `endpoint` (a string or `Vws.Links.Endpoint`) and starts a client linked to
  the caller. Retries for `:connect_timeout` ms.
  """
  @spec connect(Vws.Links.Transport.endpoint(), keyword) :: {:ok, client} | {:error, term}
  def connect(endpoint, opts \\ []) do
    with {:ok, conn} <- connect_retrying(endpoint, Keyword.get(opts, :connect_timeout, 5_000)),
         {:ok, pid} <- :gen_statem.start_link(Connection, {conn, endpoint, opts}, []) do
      case Vws.Links.Transport.controlling_process(conn, pid) do
        :ok ->
          :ok = :gen_statem.call(pid, :activate)
          {:ok, pid}

        {:error, reason} ->
          :gen_statem.stop(pid)
          Vws.Links.Transport.close(conn)
          {:error, reason}
      end
    end
  end

  defp connect_retrying(endpoint, timeout) do
    deadline = System.monotonic_time(:millisecond) + timeout
    do_connect(endpoint, deadline)
  end

  defp do_connect(endpoint, deadline) do
    case Vws.CEC.Cell.connect(endpoint) do
      {:ok, conn} ->
        {:ok, conn}

      {:error, _} = error ->
        if System.monotonic_time(:millisecond) >= deadline do
          error
        else
          Process.sleep(20)
          do_connect(endpoint, deadline)
        end
    end
  end

  @doc "Closes the link and stops the client."
  @spec close(client) :: :ok
  def close(client), do: :gen_statem.stop(client)

  @doc """
  Sends commands `[{set_letter, text}]` in one string (each set at most once). Allocates the
  string's sequence number and each command's number in its set; returns the numbers once the
  CEC acknowledged the string intact (`05A`).
  """
  @spec send_commands(client, [{letter, String.t()}, ...]) ::
          {:ok, [{letter, 0..9999}]} | {:error, ClientError.t()}
  def send_commands(client, commands) when is_list(commands) do
    with :ok <- check_commands(commands) do
      request(client, {:commands, commands})
    end
  end

  @doc "Asks the status `name` (`ROBOT_CMD`, `VISE`, …) once; returns the status text."
  @spec status(client, String.t()) :: {:ok, String.t()} | {:error, ClientError.t()}
  def status(client, name) when is_binary(name) do
    case Command.check(%Command{letter: "S", set: :status, number: 0, text: name}) do
      :ok -> request(client, {:status, name})
      {:error, _} -> {:error, %ClientError{reason: :bad_request, data: "bad status name"}}
    end
  end

  @doc """
  The seed's polling rule: asks the status of command `number` of set `letter` until that number
  appears, and then until it is no longer `EXECUTING`. `:done`, or the error: the CEC's
  `ERROR <reason>` (`:command_failed`), or `:command_timeout` after `timeout` ms.
  Option `:poll_interval` (ms between queries, default 100).
  """
  @spec await_command(client, letter, 0..9999, timeout, keyword) :: :done | {:error, term}
  def await_command(client, letter, number, timeout, opts \\ []) do
    name = command_status_name(letter)
    interval = Keyword.get(opts, :poll_interval, 100)
    deadline = if timeout == :infinity, do: :infinity, else: now() + timeout

    poll(client, %{
      name: name,
      number: number,
      interval: interval,
      deadline: deadline,
      ms: timeout
    })
  end

  defp poll(client, p) do
    with {:ok, text} <- status(client, p.name) do
      set = String.replace_suffix(p.name, "_CMD", "")

      case command_status(text) do
        {:ok, number, "DONE"} when number == p.number ->
          :done

        {:ok, number, word} when number == p.number and word != "EXECUTING" ->
          {:error,
           %ClientError{reason: :command_failed, data: %{set: set, number: number, status: word}}}

        {:ok, _number, _word} ->
          if p.deadline != :infinity and now() >= p.deadline do
            {:error,
             %ClientError{
               reason: :command_timeout,
               data: %{set: set, number: p.number, last: text, ms: p.ms}
             }}
          else
            Process.sleep(p.interval)
            poll(client, p)
          end

        :error ->
          {:error, %ClientError{reason: :bad_status, data: text}}
      end
    end
  end

  @doc """
  Splits a command-status text into its number and word.

      iex> Vws.Peers.WC.Client.command_status("0009ERROR NO LINK TO VAL II")
      {:ok, 9, "ERROR NO LINK TO VAL II"}
  """
  @spec command_status(String.t()) :: {:ok, 0..9999, String.t()} | :error
  def command_status(<<digits::binary-size(4), word::binary>>) when word != "" do
    case Command.digits(digits) do
      {:ok, number} -> {:ok, number, word}
      :error -> :error
    end
  end

  def command_status(_text), do: :error

  @doc "The status command that reports commands of set `letter` (`\"R\"` → `\"ROBOT_CMD\"`)."
  @spec command_status_name(letter) :: String.t()
  def command_status_name(letter), do: Map.fetch!(@command_status_names, letter)

  @doc """
  Downloads an NC program to the CEC (`M…DOWNLOAD_HP(cccc)`, the program's CRC named). Returns
  the Monarch command once every line is acknowledged and the CEC's CRC of the whole program is
  the program's; poll it with `await_command/5` to learn that the CEC stored it.
  """
  @spec download_program(client, [String.t()]) ::
          {:ok, {letter, 0..9999}} | {:error, ClientError.t()}
  def download_program(client, lines) when is_list(lines) do
    case validate_program(lines) do
      :ok -> request(client, {:download, lines})
      {:error, why} -> {:error, %ClientError{reason: :bad_request, data: why}}
    end
  end

  @doc """
  Uploads NC_UP from the CEC (`M…UPLOAD_SUN`): the Monarch command and the program's lines,
  whose CRC is the one the CEC sent with the closing `%/cccc` (a program received otherwise is
  `{:error, %ClientError{reason: :program_crc}}`). When the CEC has nothing to send, the
  command's `ERROR NO UPLOADED PROGRAM` is returned.
  """
  @spec upload_program(client) ::
          {:ok, {letter, 0..9999}, [String.t()]} | {:error, ClientError.t()}
  def upload_program(client) do
    case request(client, :upload) do
      {:no_lines, number, timeout} ->
        # No line came: either the CEC had none to send (its command ends ERROR at once) or the
        # link is stuck; the command's status tells which.
        case await_command(client, "M", number, timeout) do
          :done -> {:ok, {"M", number}, []}
          {:error, %ClientError{reason: :command_timeout}} -> {:error, no_lines(number)}
          {:error, error} -> {:error, error}
        end

      other ->
        other
    end
  end

  defp no_lines(number) do
    %ClientError{
      reason: :transfer_failed,
      data: %{direction: :upload, line: 1, why: "no line came for MONARCH command #{number}"}
    }
  end

  @doc """
  Whether `lines` can be sent as a DOWNLOAD_HP program: printable ASCII lines of at most 1021
  characters, ending with a `%` line, with no other `%` line except a leading one (the tape's
  rewind stop), which the CEC would take for the end.

      iex> Vws.Peers.WC.Client.validate_program(["%", "O001234", "N10 G00 X0", "%"])
      :ok
      iex> Vws.Peers.WC.Client.validate_program(["O001234", "N10 G00 X0"])
      {:error, "the last line must be % (the end of the program)"}
  """
  @spec validate_program([String.t()]) :: :ok | {:error, String.t()}
  def validate_program(lines) when is_list(lines) do
    indexed = Enum.with_index(lines, 1)
    last = length(lines)

    cond do
      lines == [] ->
        {:error, "the program is empty"}

      bad = Enum.find(indexed, fn {l, _} -> not printable?(l) end) ->
        {:error, "line #{elem(bad, 1)} holds a character the WC link cannot carry"}

      long = Enum.find(indexed, fn {l, _} -> byte_size(l) > @max_program_line end) ->
        {:error, "line #{elem(long, 1)} is longer than #{@max_program_line} characters"}

      String.trim(List.last(lines)) != "%" ->
        {:error, "the last line must be % (the end of the program)"}

      not Enum.any?(lines, &(String.trim(&1) != "%")) ->
        {:error, "the program has no line but %"}

      early = Enum.find(indexed, fn {l, i} -> i > 1 and i < last and String.trim(l) == "%" end) ->
        {:error, "line #{elem(early, 1)} is a %: the CEC would end the program there"}

      true ->
        :ok
    end
  end

  defp printable?(<<b, rest::binary>>) when b in 0x20..0x7E, do: printable?(rest)
  defp printable?(<<>>), do: true
  defp printable?(_), do: false

  @doc """
  Subscribes `pid` to the event log: it receives `{:wc_client, client, %Vws.Peers.WC.Client.Event{}}`
  for every line sent or received and every note, in order, until it exits.
  """
  @spec subscribe(client, pid) :: :ok
  def subscribe(client, pid \\ self()), do: :gen_statem.call(client, {:subscribe, pid})

  @doc "Adds a remark to the event log (in order with the lines), e.g. the script step begun."
  @spec note(client, String.t()) :: :ok
  def note(client, text) when is_binary(text), do: :gen_statem.call(client, {:note, text})

  @doc "The most recent events (up to 1 000), oldest first."
  @spec log(client) :: [Vws.Peers.WC.Client.Event.t()]
  def log(client), do: :gen_statem.call(client, :log)

  @doc """
  The client's state: `%{endpoint, peer, next_sequence, next_numbers, counters}` (`peer` nil
  while it has no link), the counters being `strings`, `commands`, `status_queries`, `resends`,
  `naks` (E received), `timeouts`, `lines_sent`, `lines_received`, `naks_sent`, `stray` (replies
  not awaited) and `reconnects`.
  """
  @spec info(client) :: map
  def info(client), do: :gen_statem.call(client, :info)

  defp request(client, request), do: :gen_statem.call(client, {:request, request})

  defp check_commands([]), do: bad("a string needs at least one command")

  defp check_commands(commands) do
    letters = Enum.map(commands, &elem(&1, 0))

    cond do
      bad = Enum.find(letters, &(not Map.has_key?(@command_status_names, &1))) ->
        bad("#{inspect(bad)} is not a command set (R M F H G V)")

      dup = Enum.find(letters, fn l -> Enum.count(letters, &(&1 == l)) > 1 end) ->
        bad("set #{dup} appears twice in one string (rule 1)")

      bad = Enum.find(commands, &(not text_ok?(&1))) ->
        bad("#{inspect(elem(bad, 1))} cannot be sent (empty, '*' or control characters)")

      true ->
        :ok
    end
  end

  defp text_ok?({letter, text}) when is_binary(text) do
    Command.check(%Command{
      letter: letter,
      set: Command.set_for_letter(letter),
      number: 1,
      text: text
    }) ==
      :ok
  end

  defp text_ok?(_), do: false

  defp bad(why), do: {:error, %ClientError{reason: :bad_request, data: why}}

  defp now, do: System.monotonic_time(:millisecond)
end
