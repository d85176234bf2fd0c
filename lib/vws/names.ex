defmodule Vws.Names do
  @moduledoc """
  Where a workstation's processes are found: every part of workstation `id` is registered in
  `Vws.Registry` as `{id, role}` (`:workstation`, `:links`, `:partitions`, `:sun_comm`,
  `:journal`, `:ge2000`, `:val`, a partition's name, …).

  The parts name themselves with `via/2` when they start, and telemetry of a link finds its
  workstation in its name with `id_of/1`. This module knows nothing of what the parts are, so
  every layer can use it: the supervisor (`Vws.CEC.Workstation`) that starts them sits above them all.

      iex> Vws.Names.via("VWS-1", :sun_comm)
      {:via, Registry, {Vws.Registry, {"VWS-1", :sun_comm}}}
      iex> Vws.Names.whereis("no-such-workstation", :sun_comm)
      nil
  """

  @doc "The `{:via, Registry, …}` name of part `role` of workstation `id`."
  @spec via(term, term) :: {:via, Registry, {Vws.Registry, {term, term}}}
  def via(id, role), do: {:via, Registry, {Vws.Registry, {id, role}}}

  @doc """
  The workstation id inside a name made for one of its parts (a link's `{:via, Registry, …}`
  name), or nil for any other name: telemetry metadata of links carries it.

      iex> Vws.Names.id_of({:via, Registry, {Vws.Registry, {"VWS-1", :ge2000}}})
      "VWS-1"
      iex> Vws.Names.id_of(self())
      nil
  """
  @spec id_of(term) :: term | nil
  def id_of({:via, Registry, {Vws.Registry, {id, _role}}}), do: id
  def id_of(_name), do: nil

  @doc """
  The role inside a name made by `via/2`, or nil for any other name.

      iex> Vws.Names.role_of(Vws.Names.via("VWS-1", :ge2000))
      :ge2000
      iex> Vws.Names.role_of({"VWS-1", 9})
      nil
  """
  @spec role_of(term) :: term | nil
  def role_of({:via, Registry, {Vws.Registry, {_id, role}}}), do: role
  def role_of(_name), do: nil

  @doc "The pid of a workstation's supervisor or one of its parts, or nil."
  @spec whereis(term, term) :: pid | nil
  def whereis(id, role \\ :workstation) do
    case Registry.lookup(Vws.Registry, {id, role}) do
      [{pid, _}] -> pid
      [] -> nil
    end
  end

  @doc "The ids of the workstations running on this node, sorted."
  @spec workstations() :: [term]
  def workstations do
    Registry.select(Vws.Registry, [{{{:"$1", :workstation}, :_, :_}, [], [:"$1"]}]) |> Enum.sort()
  end

  @doc """
  The ETS table of a workstation's mailboxes (CMD_IN, the locations, the event counters), as its
  owner registered it; raises `ArgumentError` when the workstation has none (not started).

  A process that called `keep_mailbox_table/1` for `ws` gets it without a Registry look-up
  while the table's owner lives; once the owner is gone it is looked up again.
  """
  @spec mailbox_table(term) :: :ets.tid()
  def mailbox_table(ws) do
    case Process.get({__MODULE__, :mailbox, ws}) do
      nil ->
        lookup_mailbox_table(ws)

      {owner, table} ->
        if Process.alive?(owner), do: table, else: keep_mailbox_table(ws)

      :kept ->
        keep_mailbox_table(ws)
    end
  end

  @doc """
  Keeps the workstation's mailbox table (and its owner) in the calling process, for the
  processes that read and write the mailboxes at every poll or string (VWS_STATUS, SUN_COMM):
  `mailbox_table/1` then needs no Registry look-up. The owner is checked alive at every use, so
  a table whose owner was restarted is never used: the new one is looked up (and kept).
  """
  @spec keep_mailbox_table(term) :: :ets.tid()
  def keep_mailbox_table(ws) do
    case Registry.lookup(Vws.Registry, {ws, :mailbox}) do
      [{owner, table}] ->
        Process.put({__MODULE__, :mailbox, ws}, {owner, table})
        table

      [] ->
        # asked for again at the next use
        Process.put({__MODULE__, :mailbox, ws}, :kept)
        no_mailboxes(ws)
    end
  end

  defp lookup_mailbox_table(ws) do
    case Registry.lookup(Vws.Registry, {ws, :mailbox}) do
      [{_owner, table}] -> table
      [] -> no_mailboxes(ws)
    end
  end

  defp no_mailboxes(ws),
    do: raise(ArgumentError, "workstation #{inspect(ws)} has no mailboxes (is it started?)")
end
