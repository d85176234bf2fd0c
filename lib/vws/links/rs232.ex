defmodule Vws.Links.RS232 do
  @moduledoc """
  A plain RS-232 DNC port (profile `rs232-xonxoff`, docs/serial.md): the line to a CNC control
  that takes programs as text framed by `%` (`Vws.Links.RS232.Framing`) under XON/XOFF flow
  control, as most controls in service do. One process per line; MONARCH reaches it through the
  `Vws.Links.ProgramPort` seam, as it reaches the GE-2000's `Vws.Links.DNC`.

  ## What the control can do, and what this link does

  | request (DNC operation) | on the line | answer |
  |-------------------------|-------------|--------|
  | send a program (`:part_program`, DOWNLOAD_GE) | [wait for DC1] the framed program, paced, stopped by XOFF | `{:ok, []}` once the control's read-back is the very bytes sent (`verify: :read_back`, default) |
  | drip feed (`:download_execute`, DRIP_FEED) | the same, the control running it as it arrives | `{:ok, []}` once every byte is sent; nothing is kept, nothing read back |
  | receive a program (`:receive`, `:part_program`, UPLOAD_GE) | waits for the operator to punch it at the control | `{:ok, [text]}`, the program named; another program is refused |
  | status report, directory, select, delete, tool offsets | — | refused in words: a plain RS-232 control cannot be asked |

  A program the control sends unasked (the operator pressed PUNCH) goes to the owner as the DNC
  link's `{:dnc, link, {:received, command, [text]}}`, named by its program number.

  **Flow control.** DC3 (XOFF) from the control stops sending within one chunk; DC1 (XON)
  resumes it. An XOFF that lasts longer than `xoff_timeout` ends the request
  `XOFF FROM THE CONTROL FOR OVER n S` — a bounded wait, never a hang. DC1 and DC3 are never
  data. Sending is paced at the line's speed (the endpoint's `baud`, else option `baud`), in
  chunks of `chunk` bytes, so that an XOFF finds little in flight over a socket or a pty that
  would otherwise take everything at once.

  **Verification.** Plain RS-232 carries no check of any kind. A download is DONE only when the
  control has punched the program back (`read_back_timeout`, the operator's PUNCH or a control's
  auto-punch) and it is byte for byte the text sent; else `PROGRAM VERIFY FAILED READ BACK
  DIFFERS` or `PROGRAM NOT VERIFIED NO READ BACK WITHIN n S`. `verify: :none` is the shop's own
  choice to trust the line (documented as such); a drip feed cannot be read back.

  ## Options (`start_link/1`)

  `name`, `owner`, `endpoint`, `connect` (as `Vws.Links.DNC`), `framing` (the options of
  `Vws.Links.RS232.Framing.new/1`), `wait_dc1` (false), `dc1_timeout` (10 000 ms),
  `xoff_timeout` (10 000 ms), `verify` (`:read_back` | `:none`), `read_back_timeout` (30 000 ms),
  `upload_timeout` (120 000 ms), `baud` (9600, when the endpoint has none), `chunk` (8 bytes),
  `max_text` (256), `connect_timeout`, `backoff_min`, `backoff_max`.

  **Progress.** A program going out is told to the owner every 256 bytes and at its end as the
  DNC link's `{:dnc, link, {:progress, payload}}` (the payload of `Vws.Links.DNC`'s
  `:dnc_progress`; `pauses` counts the XOFFs).

  ## Telemetry

  `[:vws, :rs232, :transfer]` (`bytes`, `duration`; `link, direction, operation, result`) at the
  end of every program sent or received; `[:vws, :rs232, :xoff]` (`count`; `link`) for each XOFF.
  """
  @behaviour Vws.Links.ProgramPort

  alias Vws.Links.RS232.Link

  @doc false
  def child_spec(opts) do
    %{
      id: Keyword.get(opts, :id, {__MODULE__, Keyword.get(opts, :name, make_ref())}),
      start: {__MODULE__, :start_link, [Keyword.delete(opts, :id)]},
      shutdown: 5_000
    }
  end

  @doc "Starts the link (options above); bad options raise `Vws.Options.Error` or `ArgumentError`."
  @spec start_link(keyword) :: :gen_statem.start_ret()
  def start_link(opts), do: Link.start_link(opts)

  @impl true
  @doc "One request (see the table above); `timeout` bounds the caller's wait."
  def request(link, command, text_blocks, timeout \\ :infinity) do
    :gen_statem.call(link, {:request, command, text_blocks}, timeout)
  catch
    :exit, {:timeout, _} -> {:error, "RS-232 REQUEST TIMED OUT"}
    :exit, _ -> {:error, "RS-232 LINK DOWN"}
  end

  @impl true
  def max_text(link), do: info(link).max_text

  @impl true
  def set_owner(link, pid), do: :gen_statem.call(link, {:set_owner, pid})

  @impl true
  @doc "State, endpoint, peer and counters (`xoffs`, `programs_sent`, `programs_received`, …)."
  def info(link), do: :gen_statem.call(link, :info)

  @doc "Hands the link an open connection (a listener's, a test's)."
  @spec attach(:gen_statem.server_ref(), Vws.Links.Transport.Conn.t()) :: :ok
  def attach(link, conn) do
    :ok = Vws.Links.Transport.controlling_process(conn, GenServer.whereis(link) || link)
    :gen_statem.call(link, {:attach, conn})
  end
end
