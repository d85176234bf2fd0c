defmodule Vws.Links.DNC do
  @moduledoc """
  The GE-2000 DNC Level 2 link (PROTOCOLS.md §2, seed §3.1–3.2.7): one process per line, used by
  both ends — MONARCH on the CEC (`role: :cec`, master by default) and the simulated VMC,
  `Vws.Sim.GE2000` (`role: :ge`). Frames are `Vws.Links.DNC.Frame`'s; this module is the protocol.

  ## The protocol as this link speaks it

      CEC (request SNS)                  GE-2000
      ENQ                        →
                                 ←       DLE 0
      SOH S N S STX ETX BCC      →
                                 ←       DLE 1
      STX program… ETX BCC       →                       (every text block, ≤ max_text bytes)
                                 ←       DLE 0 / DLE 1 …  (alternating)
      EOT                        →

  A request whose command is `R…` (RNS, RNO, RNL) continues: after our EOT the GE-2000 bids with
  `ENQ DEL`, we answer `DLE 0` and acknowledge its text blocks `DLE 1`, `DLE 0`, … until its
  `EOT DEL`; `request/4` then returns those blocks. (Decision: when no bid comes within
  `reply_timeout`, our EOT may have been lost on the line and the GE-2000 still waits for it: EOT
  is sent again, at most `max_enqs` times, until `response_timeout`.)

    * **Contention**: when our bid meets the peer's ENQ, the `:cec` role yields (answers ACK0,
      receives the peer's transmission, then bids again); the `:ge` role keeps the line.
    * **NAK** → the block is sent again, at most `max_naks` times.
    * **No reply** within `reply_timeout` → ENQ ("repeat your reply"), at most `max_enqs` times.
      If the repeated reply is the previous acknowledgement, the block was lost: it is sent again
      (counted like a NAK). An acknowledgement of the wrong parity out of the blue is a lost reply.
    * **WACK** → wait `wack_delay`, then ENQ; at most `max_wacks` WACKs running (a drip feed's
      wait is the machine's pace, at most `wack_delay`: see Drip feed).
    * When a limit is reached the link sends EOT and the request ends `{:error, %Vws.Links.DNC.LinkError{}}`.
      A transmission either completes with every block acknowledged or ends with an error; a
      receiver never hands on a partial transmission.
    * A bad block received (bad BCC, malformed — a control inside it, which makes it one error,
      see `Vws.Links.DNC.Frame`) is answered NAK; ENQ is answered by repeating the last reply. An EOT
      right after our NAK or WACK means the sender gave up: what arrived is not handed on as a
      transmission (a request waiting for it ends `:aborted`).
    * **Every block counts once.** Blocks carry no number; the ACK0/ACK1 alternation is what
      tells a copy from the next block. A block equal to the last one accepted, while a copy of
      it may still come (one per NAK we sent for it, and at least one for an ACK the sender did
      not see or misread), is answered with that block's ACK again and dropped; a block after our
      NAK replaces nothing accepted. A new block that merely repeats the last one's text is
      answered the same way at first: the sender finds the parity wrong, asks with ENQ, gets the
      same ACK and sends it again, and then it is taken — a round trip lost, never a block.
    * Limit of the line discipline (no ETB in this link): when a sender gives up after its
      acknowledgements were lost, the receiver cannot tell that EOT from a normal end.

  ## Options (`start_link/1`)

    * `:name` — a registered name (`{:via, Registry, …}` welcome)
    * `:endpoint` — connect to this endpoint (`tcp://h:p`, `tty:/dev/x?baud=4800`, `loopback:n`)
      and reconnect with backoff (`backoff_min` 100 ms doubling to `backoff_max` 5 000 ms, back
      to the minimum only once the peer has sent a frame on a connection — `Vws.Links.Backoff`;
      `connect_timeout` 2 000 ms) whenever the peer goes away. Without it the link waits to be
      given a connection with `attach/2` (a listener's accepted connections, say).
    * `:connect` — more options for `Vws.Links.Transport.connect/2` when dialling `:endpoint`
      (`transport:`, the transport that reaches it)
    * `:conn` — an open `Vws.Links.Transport` connection of the caller's, handed to the link at start
    * `:role` — `:cec` (default) or `:ge` (pads ENQ and EOT with DEL and wins contention; both can
      be set alone with `pad:` and `win_contention:`)
    * `:owner` — a pid told what happens on the link (below)
    * limits and timers, with their defaults (PROTOCOLS.md §2 where it says):
      `reply_timeout` 3 000 ms, `max_naks` 3, `max_enqs` 3 (also the bid's re-tries), `wack_delay`
      2 000 ms, `max_wacks` 3, `max_contention` 3 (yields running), `response_timeout` 10 000 ms
      (after our `R` command's EOT, for the peer's bid), `receive_timeout` 10 000 ms (between
      received blocks), `answer_timeout` 5 000 ms (for the owner's `answer/3`), `max_text` 256
      bytes per block, `max_receive` 4 MiB per received transmission (not for `E`, which keeps
      nothing), `receive_buffer` (see Drip feed).
    Pacing and fault injection are the simulators' (`Vws.Sim.GE2000`, `Vws.Sim.Line`), which put
    their own transports under a link (`Vws.Sim.Tap`), never a hook in it.

  Checked by `start_link/1` (`Vws.Options`): an unknown option or a bad value raises
  `Vws.Options.Error` naming it.

  ## Messages to the owner

  `{:dnc, link_pid, event}` with event one of:

    * `:connected`, `:disconnected`
    * `{:received, %Vws.Links.DNC.Frame.Command{direction: :send}, text_blocks}` — the peer sent an `S`
      command and its text, all acknowledged (the peer has already given EOT)
    * `{:request, ref, %Vws.Links.DNC.Frame.Command{direction: :receive}, text_blocks}` — the peer sent an
      `R` command: answer with `answer(link, ref, text_blocks)` within `answer_timeout`; the link
      bids and sends them
    * `{:unsolicited, text_blocks}` — the peer bid and sent text without a command
    * `{:aborted, command | nil, text_blocks}` — the peer gave its transmission up (EOT right
      after our NAK or WACK): not a whole transmission, only for the record
    * `{:answer_failed, %Vws.Links.DNC.LinkError{}}` — an answer could not be delivered
    * `{:block, command, index, text}` — a text block of an `E` (drip feed) transmission, as it
      is taken (index counts the command block as 1)

  ## Telemetry

  | event | measurements | metadata |
  |-------|--------------|----------|
  | `[:vws, :dnc, :connected]` / `:disconnected` | `count` | `link, workstation, role, peer` (+ `reason`) |
  | `[:vws, :dnc, :connect_failed]` | `count`, `retry_in` (ms to the next attempt) | `link, workstation, role, endpoint, reason` |
  | `[:vws, :dnc, :block_sent]` | `bytes` | `link, workstation, role, block, retransmission` |
  | `[:vws, :dnc, :block_received]` | `bytes` | `link, workstation, role, block` |
  | `[:vws, :dnc, :retry]` | `count` | `link, workstation, role, kind` (`:nak_received`, `:nak_sent`, `:wack_received`, `:no_reply`, `:lost_reply`, `:duplicate_received`, `:eot_again`), `block` |
  | `[:vws, :dnc, :transmission]` | `duration` (native), `blocks`, `bytes` | `link, workstation, role, direction, result` (+ `kind`) |

  | `[:vws, :dnc, :progress]` | `blocks, bytes, program_bytes, chars_per_s, retries` | `link, workstation, role, program, operation, direction, total_blocks, total_bytes, total_program_bytes, eta_s, ended` (false, or `:ok`/the failure) |

  ## Transfer progress

  While an NC program goes over the link (`SxS`, `RxS`, `SxE` — not the status reads), every
  block acknowledged or taken, and the transfer's end, is published: as the telemetry event
  `[:vws, :dnc, :progress]` above and, for a link named in a workstation, as the workstation's
  event `:dnc_progress` on `Vws.CEC.Events`:

      {:vws_event, workstation, :dnc_progress,
       %{link, program, operation, direction, blocks, total_blocks, bytes, total_bytes,
         program_bytes, total_program_bytes, chars_per_s, eta_s, retries, ended}}

  (`total_*` nil for a reception; `ended` false while it runs, and once, at its end, `:ok` or
  the reason it failed, with its last figures). `progress/1`
  (and `info/1`'s `transfer`) give the same figures on request (`Vws.Links.DNC.Progress`).

  ## Drip feed (ours)

  A `download_execute` (`E`) transmission is streamed: the receiving link hands each text block
  to its owner as `{:block, command, index, text}` when it takes it, keeps none of them, and
  meters them against `receive_buffer` (bytes, option; `:infinity` — no flow control — by
  default): once less than `max_text` of it is left, the block is acknowledged WACK, and so is
  an ENQ, until the owner gives room back with `grant/2`. The sending link waits out any number
  of WACKs in an `E` transmission, asking again with ENQ when the machine has run about one block
  at the consumption rate it measured (`Vws.Links.DNC.Pace`; at most `wack_delay`); in any
  other, `max_wacks` holds, `wack_delay` apart. See docs/dnc-drip-feed.md.

  `workstation` is the id in a `Vws.CEC.Workstation` name given as `:name` (`Vws.Names.id_of/1`), else nil.

  ## Example

      iex> {:ok, listener} = Vws.Links.Transport.listen("loopback:dnc-doc")
      iex> {:ok, ge} = Vws.Links.DNC.start_link(role: :ge, owner: self())
      iex> {:ok, cec} = Vws.Links.DNC.start_link(endpoint: "loopback:dnc-doc")
      iex> {:ok, conn} = Vws.Links.Transport.accept(listener, 1_000)
      iex> :ok = Vws.Links.DNC.attach(ge, conn)
      iex> status = %Vws.Links.DNC.Frame.Command{direction: :receive, operation: :status}
      iex> task = Task.async(fn -> Vws.Links.DNC.request(cec, status, [], 5_000) end)
      iex> receive do {:dnc, ^ge, {:request, ref, ^status, []}} -> Vws.Links.DNC.answer(ge, ref, ["STATE=IDLE;PROG=000000;ALARM=0"]) end
      :ok
      iex> Task.await(task)
      {:ok, ["STATE=IDLE;PROG=000000;ALARM=0"]}
  """

  alias Vws.Links.DNC.{Frame, LinkError}

  @type link :: :gen_statem.server_ref()
  @doc false
  def child_spec(opts) do
    %{
      id: Keyword.get(opts, :id, {__MODULE__, Keyword.get(opts, :name, make_ref())}),
      start: {__MODULE__, :start_link, [Keyword.delete(opts, :id)]},
      shutdown: 5_000
    }
  end

  @doc "Starts a link process (see the options above)."
  @spec start_link(keyword) :: :gen_statem.start_ret()
  def start_link(opts) do
    {conn, opts} = Keyword.pop(opts, :conn)

    with {:ok, pid} <- Vws.Links.DNC.Link.start_link(opts) do
      if conn, do: :ok = attach(pid, conn)
      {:ok, pid}
    end
  end

  @doc """
  Sends `command` and its `text_blocks` (each at most `max_text` bytes, no transmission control
  characters) as master, and returns when the transmission is over: `{:ok, []}` for an `S`
  command; for an `R` command `{:ok, blocks}`, the text blocks the peer sent back.

  Waits while the link is busy (the request is postponed until it is idle); answers
  `{:error, %LinkError{reason: :link_down}}` at once while there is no connection. `timeout`
  (ms or `:infinity`) is the caller's deadline, waiting for the line included: a request still
  waiting when it passes is never bid for, one under way is ended (EOT), and
  `{:error, %LinkError{reason: :timeout}}` is returned — an answer after it never reaches the
  caller (`Vws.Links.Connection`). The protocol's own limits always end a request anyway.
  """
  @spec request(link, Frame.Command.t(), [binary], timeout) ::
          {:ok, [binary]} | {:error, LinkError.t()}
  def request(link, %Frame.Command{} = command, text_blocks, timeout \\ :infinity)
      when is_list(text_blocks) do
    case Vws.Links.Connection.call(link, {:request, command, text_blocks}, timeout) do
      {:error, :timeout} -> {:error, %LinkError{reason: :timeout}}
      called -> result(called)
    end
  end

  @doc """
  `request/4` without waiting: the answer arrives as a message to the caller, which
  `check_response/2` reads (for an owner that must stay free meanwhile, as the simulated
  GE-2000 does while its panel's request is out). The link ends the request by `timeout`.
  """
  @spec send_request(link, Frame.Command.t(), [binary], timeout) :: term
  def send_request(link, %Frame.Command{} = command, text_blocks, timeout \\ :infinity)
      when is_list(text_blocks),
      do: Vws.Links.Connection.send_request(link, {:request, command, text_blocks}, timeout)

  @doc """
  Whether `msg` is the answer to the request `request_id` (`send_request/4`): what `request/4`
  would have returned, or `:no_reply` for any other message.
  """
  @spec check_response(term, term) :: {:ok, [binary]} | {:error, LinkError.t()} | :no_reply
  def check_response(msg, request_id) do
    case Vws.Links.Connection.check_response(msg, request_id) do
      :no_reply -> :no_reply
      checked -> result(checked)
    end
  end

  defp result({:ok, result}), do: result
  defp result({:error, {:exit, _reason}}), do: {:error, %LinkError{reason: :link_down}}

  @doc "Answers the peer's `R` command announced to the owner as `{:request, ref, command, blocks}`."
  @spec answer(link, reference, [binary]) :: :ok | {:error, :not_asked | LinkError.t()}
  def answer(link, ref, text_blocks) when is_list(text_blocks) do
    :gen_statem.call(link, {:answer, ref, text_blocks})
  end

  @doc """
  Hands an open `Vws.Links.Transport` connection, owned by the caller, to the link. A connection the
  link already had is closed, and whatever was in progress on it ends `:link_down`.
  """
  @spec attach(link, Vws.Links.Transport.Conn.t()) :: :ok | {:error, term}
  def attach(link, conn) do
    pid = GenServer.whereis(link)

    with :ok <- Vws.Links.Transport.controlling_process(conn, pid) do
      :gen_statem.call(pid, {:attach, conn})
    end
  end

  @doc """
  The link's state (`:disconnected`, `:idle`, `:bidding`, `:sending`, `:turnaround` — waiting for
  the peer's bid after our `R` command —, `:receiving`, `:answering` — the owner preparing the
  answer to the peer's `R` command), role, endpoint, peer, block size, counters and the
  transfer under way (`progress/1`).
  """
  @spec info(link) :: map
  def info(link), do: :gen_statem.call(link, :info)

  @doc "The largest text block the link sends or accepts."
  @spec max_text(link) :: pos_integer
  def max_text(link), do: info(link).max_text

  @doc """
  The transfer under way on the link, or nil: program, direction, blocks and bytes done and in
  all, retries, characters a second and ETA (`Vws.Links.DNC.Progress`).
  """
  @spec progress(link) :: map | nil
  def progress(link), do: info(link).transfer

  @doc """
  Bids and sends `text_blocks` without a command block, as master (waits while the link is
  busy). For a simulated peer that sends of its own accord.
  """
  @spec transmit(link, [binary]) :: :ok | {:error, term}
  def transmit(link, text_blocks) when is_list(text_blocks),
    do: :gen_statem.call(link, {:transmit, text_blocks})

  @doc """
  Gives `bytes` back to the credit of the `E` (download and execute) reception under way: the
  receiver has run that much of the program (see "Drip feed" above).
  """
  @spec grant(link, non_neg_integer) :: :ok
  def grant(link, bytes) when is_integer(bytes) and bytes >= 0,
    do: :gen_statem.call(link, {:grant, bytes})

  @doc "Makes `pid` the link's owner, told what happens on the link (see above)."
  @spec set_owner(link, pid | nil) :: :ok
  def set_owner(link, pid), do: :gen_statem.call(link, {:set_owner, pid})
end
