defmodule Vws.CEC.Mailbox.Recorder do
  @moduledoc """
  What the mailboxes give every change to before it is visible: a module implementing these
  callbacks, attached to a workstation's table with `Vws.CEC.Mailbox.attach_recorder/2`
  (`Vws.CEC.Journal`, which makes each change durable).

  The mailbox does not know who records; without a recorder, nothing is. This module holds only
  the callbacks and depends on nothing, so a recorder compiles against it without recompiling
  when the mailboxes change.
  """

  @doc "Makes `record` durable (the command journal); `{:error, reason}` when it could not."
  @callback record(:ets.tid(), record :: tuple) :: :ok | {:error, term}

  @typedoc """
  A program as it is made durable: its lines, or `{:library, name, version, digest}` — a
  version of the workstation's program library (`Vws.CEC.Library`) that holds exactly these
  lines already, recorded by reference instead of as a second copy.
  """
  @type program :: [binary] | {:library, String.t(), pos_integer, binary}

  @doc "Stores a program (`:nc_file` or `:nc_up`) durably, whole or not at all."
  @callback store_lines(:ets.tid(), :nc_file | :nc_up, program) :: :ok | {:error, term}
end
