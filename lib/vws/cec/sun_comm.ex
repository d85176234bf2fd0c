defmodule Vws.CEC.SunComm do
  @moduledoc """
  SUN_COMM (seed §2.3.1–2.3.7): owns the link to the workstation controller (WC), checks every
  string's BCC and answers `05A…` or `E` at once, applies the Parser's rules, hands each command to
  its partition (CMD_IN + CAUSE EVENT) and answers status commands from the mailboxes alone.

  ## The link

  One WC at a time, as on a serial line. On a tty it opens the device and reopens it if it goes
  away. On a TCP (or loopback) endpoint SUN_COMM listens, under this policy (decisions; issue 16):

    * **who may connect**: loopback only, unless `:allow` lists the addresses and networks that
      may (`Vws.Links.Transport.Policy`); listening on an address that is not loopback without an
      allow-list is refused at start. Others are closed by the acceptor before SUN_COMM sees them.
    * **takeover**: a new connection replaces the current WC only when the current one has been
      silent (nothing received) for `:takeover_after` ms; otherwise the newcomer is closed. A WC
      that restarts after losing its link without a close (a half-open connection) gets in after
      that time. Every takeover and every refusal is logged with both peers.
    * **send timeout**: an answer the WC has not made room for within `:send_timeout` ms closes
      the connection (a WC that never reads is dropped; SUN_COMM is blocked at most that long).

  Nothing is read before the workstation has caused OK_TO_PROCEED.

  ## Rules (PROTOCOLS.md §1)

    1. a command-set letter appears at most once in a string;
    2. a string with an S command contains nothing else;
    3. a command for a set whose previous command is in flight is not run: `ERROR BUSY <previous>`;
    4. a string that repeats the last accepted sequence number with the same bytes is a
       retransmission: acknowledged again, nothing executed. With other bytes it is a new string
       from a WC that restarted and numbers from where it began again (decision, issue 15): it is
       handled as any new string. (A resend damaged so that its BCC still matches cannot be told
       from it; the BCC is the link's only check, as everywhere else on this link.)
    5. an intact string that breaks a rule is acknowledged, nothing in it runs, and each of its
       commands answers `ERROR <rule>` on its next status query. A command for a set letter the
       CEC does not know (`Q0005…`) breaks the rule `UNKNOWN COMMAND SET Q`: its error is
       queryable as status `Q_CMD` (`0005ERROR UNKNOWN COMMAND SET Q`), and every other command
       of that string answers the same error under its own status (decision, issue 15).

  ## Lines that are no string (decision, issue 15)

  An empty line and a line over `:max_line` bytes (1024) are answered `E` at once — the long one
  as soon as its 1025th byte arrives, not when its LF does; the rest of it, up to its LF, is
  discarded without a further answer. A line whose end never comes is dropped and answered `E`
  after `:partial_line_timeout`.

  ## NC line transfers (PROTOCOLS.md §1 "NC download", "NC upload")

  Program lines are numbered: `nnnn` + text + BCC, answered `A` + `nnnn` + BCC (stored) or `E`
  (damaged). After acknowledging a string carrying `M…DOWNLOAD_HP`, SUN_COMM reads lines 0001,
  0002, … until the closing `%` (a `%` as the very first line is the tape's leading rewind stop and
  is kept). A line carrying the number just stored is a resend after a damaged answer: answered
  again, not stored twice; any other number ends the command `ERROR PROGRAM LINE OUT OF ORDER`. The
  closing `%` is answered `A` + the number of lines stored + `/` + their CRC-16/ARC
  (`Vws.Codecs.WC.ProgramCRC`). When the WC named the program's CRC (`DOWNLOAD_HP(cccc)`,
  PROTOCOLS.md §1 "Whole-program check") and it is not the CRC of what came, the command ends
  `ERROR PROGRAM CRC <came> EXPECTED <named>`; a program over 999,999 bytes ends
  `ERROR PROGRAM TOO LARGE <n> BYTES (LIMIT 999999)` (`Vws.Links.DNC.Program.check_size/1`); in
  both cases nothing is stored. Otherwise the program is stored in the
  workstation's program library (`Vws.CEC.Library.store_download/2`, when it has one) and
  journaled as the NC file (by the library's version when it went there, `Vws.CEC.Journal`,
  "Programs"), and the Monarch command ends `DONE`; a resend of that closing line after the command ended is
  answered the same again. After acknowledging `M…UPLOAD_SUN` it sends NC_UP line by line; a line
  answered `E`, with a damaged answer, with another number or not at all is sent again (at most
  `:upload_retries` times); the closing line carries the program's CRC, `%/cccc`; the command
  ends `DONE` when the WC has answered the closing `%` with its number (`ERROR NO UPLOADED PROGRAM` when NC_UP is empty). A status query during an upload is
  answered and the upload goes on (a WC that took the closing line asks its command's status
  while its answer reached us damaged: the closing line goes again, it answers again); any other
  string during a transfer means the WC left it. A transfer that stalls or loses the link ends
  the Monarch command `ERROR` with the reason.

  ## Options

    * `:workstation` (required), `:wc` — endpoint string or `nil` (no link)
    * `:bcc` — `:sum` (default) or `:xor`
    * `:max_line` — longest line accepted, default 1024 bytes
    * `:allow` — who may connect: `Vws.Links.Transport.Policy` allow-list (`"10.0.0.5,10.0.0.0/24"`;
      default loopback only)
    * `:takeover_after` — ms of silence of the current WC after which a new connection may
      replace it (10 000)
    * `:takeover_grace` — ms a new connection refused by that rule waits for the current WC's
      connection to end before it is closed (500): a WC that closes one connection and opens
      the next at once (`bin/vws-wc`, `socat` per command) is let in, not refused for the close
      SUN_COMM had not yet seen
    * `:send_timeout` — ms an answer may wait for the WC to read before the link is dropped (5 000)
    * `:download_timeout` — ms without a program line before a download is abandoned (30 000)
    * `:upload_timeout` — ms to wait for the WC's `A`/`E` to an uploaded line (5 000)
    * `:upload_retries` — resends of one uploaded line before giving up (5)
    * `:max_program_bytes` — the most SUN_COMM holds during a download (4 MiB): beyond it the
      download ends at once; a program is stored only up to 999,999 bytes (PROTOCOLS.md §2)
    * `:tty_retry` — ms between attempts to (re)open a tty (1 000)
    * `:partial_line_timeout` — ms of silence after the start of a line before the unfinished
      line is dropped and answered `E` (500; decision: a CR LF damaged on the line would
      otherwise leave a program-line transfer waiting)

  The options are checked once, by `start_link/1` (and by `Vws.CEC.Workstation` for its `sun_comm:`
  options, before anything starts) against one schema (`options_schema/0`): an unknown option or
  a bad value raises `Vws.Options.Error` naming it. Listening where the policy forbids it is not
  a programmer's error but a deployment's: `start_link/1` returns
  `{:error, {:wc_link_policy, message}}`.

  ## The core and the process

  The Parser's rules and both transfers are a pure core, `Vws.CEC.SunComm.Session`: each line,
  expired timer or lost link goes in, replies and effects (journal, dispatch, statuses, the
  program to store, the end of a transfer, timers) come out as data, in order. The process
  (`Vws.CEC.SunComm.Server`, a `:gen_statem`) keeps the link and carries them out; a command
  goes to its partition through `Vws.CEC.Partition.dispatch/4` (CMD_IN and the partition's
  event), never by SUN_COMM causing another partition's event.

  Its states are SUN_COMM's modes (the session's); the link (listener, acceptor, the WC
  connection) is data beside them, as a WC may come and go in any mode:

  ```
  :waiting_to_proceed --OK_TO_PROCEED--> :command              (opens the link: listen or tty)
  :command  --string with M…DOWNLOAD_HP acknowledged--> :download
  :command  --string with M…UPLOAD_SUN acknowledged (NC_UP not empty)--> :upload
  :download --closing %, line out of order, too large, stall (state_timeout),
              another string, link lost or taken over--> :command
  :upload   --closing % acknowledged, retries spent (state_timeout / E / damaged answer),
              another string, link lost or taken over--> :command
  :download / :upload --the string that began it, again--> same state, transfer restarted
  ```

  Protocol timers: the transfer timers are `state_timeout`s of `:download` (no line for
  `:download_timeout`) and `:upload` (no answer for `:upload_timeout`); the timers that span
  modes are named: `{:timeout, :partial_line}`, `{:timeout, :takeover_grace}`,
  `{:timeout, :reopen_tty}`. Bytes from the WC go through `Vws.Codecs.WC.LineDecoder`; each line
  re-enters as `{:next_event, :internal, {:line, line}}`, and a string is decoded once
  (`Vws.Codecs.WC.CommandString.decode/2`) and passed on decoded.
  """

  alias Vws.CEC.SunComm.Server

  @schema [
    workstation: [type: :any, required: true],
    wc: [type: {:or, [nil, {:custom, &__MODULE__.__endpoint__/1}]}, default: nil],
    bcc: [type: {:in, [:sum, :xor]}, default: :sum],
    max_line: [type: :pos_integer, default: 1024],
    allow: [type: {:custom, &__MODULE__.__allow__/1}, default: :loopback],
    takeover_after: [type: :non_neg_integer, default: 10_000],
    takeover_grace: [type: :non_neg_integer, default: 500],
    send_timeout: [type: :pos_integer, default: 5_000],
    download_timeout: [type: :pos_integer, default: 30_000],
    upload_timeout: [type: :pos_integer, default: 5_000],
    upload_retries: [type: :non_neg_integer, default: 5],
    max_program_bytes: [type: :pos_integer, default: 4 * 1024 * 1024],
    tty_retry: [type: :pos_integer, default: 1_000],
    partial_line_timeout: [type: :pos_integer, default: 500]
  ]

  @doc false
  # `{:validated, opts}`: options the caller checked already (`Vws.CEC.Workstation`)
  def child_spec({:validated, opts}),
    do: %{id: :sun_comm, start: {__MODULE__, :start_validated, [opts]}, shutdown: 5_000}

  def child_spec(opts) do
    %{id: :sun_comm, start: {__MODULE__, :start_link, [opts]}, shutdown: 5_000}
  end

  @doc """
  Starts SUN_COMM for a workstation (see "Options"). Raises `Vws.Options.Error` for an unknown
  option or a bad value; returns `{:error, {:wc_link_policy, message}}` when it would listen on
  an address that is not loopback without an allow-list.
  """
  @spec start_link(keyword) :: :gen_statem.start_ret()
  def start_link(opts), do: opts |> validate_options!() |> start_validated()

  @doc false
  # Options that `validate_options!/1` returned.
  def start_validated(opts) do
    case check_listen(opts[:wc], opts[:allow]) do
      :ok ->
        :gen_statem.start_link(name(opts[:workstation]), Server, Map.new(opts), [])

      {:error, message} ->
        require Logger
        Logger.error("SUN_COMM cannot start: #{message}", workstation: opts[:workstation])
        {:error, {:wc_link_policy, message}}
    end
  end

  @doc "The options schema (`Vws.Options`), defaults included."
  @spec options_schema() :: Vws.Options.schema()
  def options_schema, do: @schema

  @doc """
  Checks SUN_COMM options against `options_schema/0`: the options with their defaults, or
  `{:error, %Vws.Options.Error{}}` naming the first bad one.
  """
  @spec validate_options(keyword) :: {:ok, keyword} | {:error, Vws.Options.Error.t()}
  def validate_options(opts), do: Vws.Options.validate(opts, @schema, "SUN_COMM")

  @doc "Like `validate_options/1`, raising `Vws.Options.Error`."
  @spec validate_options!(keyword) :: keyword
  def validate_options!(opts), do: Vws.Options.validate!(opts, @schema, "SUN_COMM")

  @doc false
  def __endpoint__(wc) do
    case Vws.Links.Endpoint.parse(wc) do
      {:ok, _} -> {:ok, wc}
      {:error, error} -> {:error, "expected an endpoint (#{Exception.message(error)})"}
    end
  end

  @doc false
  def __allow__(allow) do
    case Vws.Links.Transport.Policy.parse_allow(allow) do
      {:ok, allow} -> {:ok, allow}
      {:error, message} -> {:error, "expected an allow-list (#{message})"}
    end
  end

  defp check_listen(nil, _allow), do: :ok
  defp check_listen(wc, allow), do: Vws.Links.Transport.Policy.check_listen(wc, allow)

  defp name(ws), do: Vws.Names.via(ws, :sun_comm)

  @doc """
  SUN_COMM's state for inspection: endpoint, where it listens, the WC peer, the mode (`:command`,
  `{:download, number, lines}`, `{:upload, number, lines}`), the transfer's progress and counters.
  """
  @spec info(term) :: map
  def info(ws), do: :gen_statem.call(name(ws), :info)

  @doc "The endpoint SUN_COMM listens on (with the real port when port 0 was asked), or nil."
  @spec listening(term) :: Vws.Links.Endpoint.t() | nil
  def listening(ws), do: info(ws).listening

  @doc """
  Waits until SUN_COMM listens (or has its tty open) and returns the endpoint, or nil after
  `timeout` ms. Woken by the `:wc_listening` event SUN_COMM causes when it opens its link.
  """
  @spec await_listening(term, non_neg_integer) :: Vws.Links.Endpoint.t() | nil
  def await_listening(ws, timeout) do
    :ok = Vws.CEC.Events.subscribe(ws, :wc_listening)
    deadline = System.monotonic_time(:millisecond) + timeout

    try do
      case listening(ws) do
        nil ->
          receive do
            {:vws_event, ^ws, :wc_listening, endpoint} -> endpoint
          after
            max(deadline - System.monotonic_time(:millisecond), 0) -> nil
          end

        endpoint ->
          endpoint
      end
    after
      Vws.CEC.Events.unsubscribe(ws, :wc_listening)

      receive do
        {:vws_event, ^ws, :wc_listening, _} -> :ok
      after
        0 -> :ok
      end
    end
  end

  @doc "The most recent lines of the WC dialogue, oldest first: `{monotonic_ms, :in | :out, line}`."
  @spec dialogue(term) :: [{integer, :in | :out, binary}]
  def dialogue(ws), do: :gen_statem.call(name(ws), :dialogue)

  @doc """
  Runs one command of this node's operator (the dashboard's control actions) through the same
  path as a WC string's command — the Parser's rules, the journal, the partition's dispatch and
  interlocks — without the WC link: `:ok` (dispatched; its status location tells how it ends) or
  `{:error, words}`. `number` should be one the WC does not use (`Vws.Ops.Web.Command` takes them
  from 9000 up).
  """
  @spec local_command(term, String.t(), 0..9999, String.t()) :: :ok | {:error, String.t()}
  def local_command(ws, letter, number, text),
    do: :gen_statem.call(name(ws), {:local_command, letter, number, text}, 10_000)
end
