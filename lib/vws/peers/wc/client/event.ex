defmodule Vws.Peers.WC.Client.Event do
  @moduledoc """
  One entry of a `Vws.Peers.WC.Client`'s event log: a line sent or received on the WC link, or a note.

    * `at` — ms since the client connected
    * `direction` — `:sent` (WC → CEC), `:received` (CEC → WC) or `:note`
    * `line` — the line as on the wire, without CR LF (`nil` for a note)
    * `kind` — `:string`, `:status_query`, `:resend`, `:program_line`, `:line_answer` (sent);
      `:ack`, `:nak`, `:status`, `:line_ack`, `:program_line`, `:damaged`, `:stray` (received);
      `:note`, `:link` (notes)
    * `meaning` — what it means, in words: `"ack: string 0054 received intact"`,
      `"ROBOT 0009 DONE"`
  """

  @enforce_keys [:at, :direction, :kind, :meaning]
  defstruct [:at, :direction, :line, :kind, :meaning]

  @type t :: %__MODULE__{
          at: non_neg_integer,
          direction: :sent | :received | :note,
          line: String.t() | nil,
          kind: atom,
          meaning: String.t()
        }
end
