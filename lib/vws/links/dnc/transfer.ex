defmodule Vws.Links.DNC.Transfer do
  @moduledoc """
  The bookkeeping of one transfer on a DNC line, for `Vws.Links.DNC.Session`: the record of a
  transmission (`new_tx/4`: its frames, what the peer acknowledged, retries and pauses) and of
  a reception (`new_rx/2`: the blocks taken, the last acknowledgement, the last block accepted), and the view of
  either that progress reports and telemetry are made of (`view/3`). Pure data.
  """

  @typedoc "A transmission under way (the session's `tx`)."
  @type tx :: map
  @typedoc "A reception under way (the session's `rx`)."
  @type rx :: map

  @typedoc """
  The transfer under way: direction, command, blocks and bytes (on the line, blocks whole) done
  and in all, the program's text bytes done and in all (a reception's totals are not known
  before its end), retries, pauses (WACKs: the receiver asked us to wait) and its start (`now`
  units).
  """
  @type view :: %{
          direction: :out | :in,
          command: term,
          blocks: non_neg_integer,
          total_blocks: non_neg_integer | nil,
          bytes: non_neg_integer,
          total_bytes: non_neg_integer | nil,
          program_bytes: non_neg_integer,
          total_program_bytes: non_neg_integer | nil,
          retries: non_neg_integer,
          pauses: non_neg_integer,
          started: integer
        }

  @doc """
  A transmission of `kind` (`:request`, `:unsolicited`, `:answer`): the encoded `frames`, the
  program's text bytes of each (`sizes`), started at `now`.
  """
  @spec new_tx(atom, [iodata], [non_neg_integer], integer) :: tx
  def new_tx(kind, frames, sizes, now) do
    %{
      kind: kind,
      frames: List.to_tuple(frames),
      sizes: List.to_tuple(sizes),
      acked: 0,
      bids: 0,
      yields: 0,
      naks: 0,
      enqs: 0,
      wacks: 0,
      polled: false,
      confirm: nil,
      wacked: false,
      # when to ask again after a WACK (a drip feed's, Vws.Links.DNC.Pace)
      pace: Vws.Links.DNC.Pace.new(),
      retries: 0,
      pauses: 0,
      started: now,
      text_acked: 0,
      text_bytes: Enum.sum(sizes),
      bytes_acked: 0,
      bytes: Enum.reduce(frames, 0, &(IO.iodata_length(&1) + &2))
    }
  end

  @doc "A reception of `kind` (`:slave`, `:reply`) started at `now`."
  @spec new_rx(atom, integer) :: rx
  def new_rx(kind, now) do
    %{
      kind: kind,
      command: nil,
      blocks: [],
      count: 0,
      bytes: 0,
      last: :ack0,
      sent: :ack0,
      accepted: nil,
      ack: :ack0,
      retries: 0,
      ref: nil,
      started: now
    }
  end

  @doc """
  The view of the transmission `tx` or, without one, the reception `rx`; nil when neither is
  under way. `command` is the request's command block (a reception names its own once taken).
  """
  @spec view(tx | nil, rx | nil, term) :: view | nil
  def view(%{frames: frames} = tx, _rx, command) do
    %{
      direction: :out,
      command: command,
      blocks: tx.acked,
      total_blocks: tuple_size(frames),
      bytes: tx.bytes_acked,
      total_bytes: tx.bytes,
      program_bytes: tx.text_acked,
      total_program_bytes: tx.text_bytes,
      retries: tx.retries,
      pauses: tx.pauses,
      started: tx.started
    }
  end

  def view(nil, %{} = rx, command) do
    %{
      direction: :in,
      command: rx.command || command,
      blocks: rx.count,
      total_blocks: nil,
      bytes: rx.bytes,
      total_bytes: nil,
      program_bytes: rx.bytes,
      total_program_bytes: nil,
      retries: rx.retries,
      pauses: 0,
      started: rx.started
    }
  end

  def view(nil, nil, _command), do: nil
end
