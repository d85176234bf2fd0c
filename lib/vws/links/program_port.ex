defmodule Vws.Links.ProgramPort do
  @moduledoc """
  What MONARCH needs of the line to its machine tool, whatever the control speaks: the seam
  between `Vws.Partitions.Monarch` and a DNC port. Two links implement it:

    * `Vws.Links.DNC` — the GE-2000's DNC Level 2 (profile `ge2000-level2`): every request of
      PROTOCOLS.md §2 (programs, status report, directory, select, delete, tool offsets);
    * `Vws.Links.RS232` — a plain RS-232 control under XON/XOFF (profile `rs232-xonxoff`):
      programs in and out, and drip feed; every other request is refused in words
      (docs/serial.md).

  A port's profile names its link (`Vws.Links.ProgramPort.Profile`). This module holds the
  callbacks only and depends on nothing, so both links compile against it alone.

  `request/4` takes the DNC link's command (`Vws.Links.DNC.Frame.Command`: direction, operation,
  text) and text blocks, and answers `{:ok, text_blocks}` or `{:error, reason}` — the DNC link's
  `%Vws.Links.DNC.LinkError{}`, or, from a link that has no such struct, the words of an
  `ERROR` status (upper-case words and numbers).
  """

  @typedoc "A link process (pid or registered name)."
  @type link :: :gen_statem.server_ref()

  @doc "Runs one request on the line; returns once it is over (or `timeout` passed)."
  @callback request(link, command :: struct, text_blocks :: [binary], timeout) ::
              {:ok, [binary]} | {:error, struct | String.t()}

  @doc "The largest text block the link takes in one piece."
  @callback max_text(link) :: pos_integer

  @doc "Makes `pid` the process told what the machine sends unasked (`{:dnc, link, event}`)."
  @callback set_owner(link, pid) :: :ok

  @doc "The link's state and counters, for the views (`Vws.Ops.Inspect`)."
  @callback info(link) :: map
end
