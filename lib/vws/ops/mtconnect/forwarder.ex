defmodule Vws.Ops.MTConnect.Forwarder do
  @moduledoc """
  The MTConnect agent's reach into another node (`Vws.Ops.MTConnect.Agent`, "Recording"): one
  forwarder process on each node whose workstations the agent serves, and the reading of a
  workstation's mailboxes, which runs on its own node.

  The agent starts a forwarder on a node (`start/2`) and asks it to follow a workstation
  (`follow/2`); the forwarder subscribes to that workstation's change notices (`:mailbox`) and
  its GE-2000 link's transfer progress (`:dnc_progress`), reads its mailboxes once and sends
  the agent that snapshot (`{:mtc_snapshot, ws, facts}`) and its links' states
  (`{:mtc_links, ws, links, at}`, `Vws.Ops.MTConnect.LinkWatch`), then every change as it comes:
  the notices themselves (`{:vws_event, ws, …}`) and each link's change
  (`{:mtc_link, ws, key, state, at}`). `sync/2` asks it to say (`{:mtc_synced, ref}`) after all
  it has sent, so that an answer of the agent is never older than the request. A forwarder
  ends with its agent.
  """

  alias Vws.CEC.Mailbox
  alias Vws.Ops.MTConnect.LinkWatch

  @doc "Starts a forwarder for `agent` on node `n` (monitored by the caller): its pid."
  @spec start(node, pid) :: pid
  def start(n, agent) do
    pid = Node.spawn(n, __MODULE__, :run, [agent])
    Process.monitor(pid)
    pid
  end

  @doc "Asks the forwarder to follow workstation `ws`: a snapshot, then every change."
  @spec follow(pid, term) :: :ok
  def follow(pid, ws) do
    send(pid, {:follow, ws})
    :ok
  end

  @doc "Asks the forwarder to answer `{:mtc_synced, ref}` after what it has sent so far."
  @spec sync(pid, reference) :: :ok
  def sync(pid, ref) do
    send(pid, {:sync, self(), ref})
    :ok
  end

  @doc false
  # The forwarder's loop, on a workstation's node. It ends with its agent.
  def run(agent) do
    ref = Process.monitor(agent)
    # this node's links tell their changes (LinkWatch), passed on for the workstations followed
    :ok = LinkWatch.attach()
    forward_notices(agent, ref, %{}, LinkWatch.new())
  end

  defp forward_notices(agent, ref, since, watch) do
    receive do
      {:follow, ws} ->
        if not Map.has_key?(since, ws) do
          :ok = Vws.CEC.Events.subscribe(ws, :mailbox)
          :ok = Vws.CEC.Events.subscribe(ws, :dnc_progress)
        end

        t = System.system_time(:microsecond)
        send(agent, {:mtc_snapshot, ws, read(ws)})
        {watch, links, at} = LinkWatch.read(watch, ws)
        send(agent, {:mtc_links, ws, links, at})
        forward_notices(agent, ref, Map.put(since, ws, t), watch)

      {:vws_event, ws, :mailbox, {_change, at}} = notice ->
        # what was written before the snapshot was read is in it already
        case since do
          %{^ws => t} when at >= t -> send(agent, notice)
          _ -> :ok
        end

        forward_notices(agent, ref, since, watch)

      # a transfer's progress (the VMC's transfer message): told as it comes
      {:vws_event, ws, :dnc_progress, _progress} = notice ->
        if Map.has_key?(since, ws), do: send(agent, notice)
        forward_notices(agent, ref, since, watch)

      {:link_event, pid, event, meta, at} ->
        case LinkWatch.event(watch, pid, event, meta, at) do
          {:change, ws, key, state, at} ->
            send(agent, {:mtc_link, ws, key, state, at})
            forward_notices(agent, ref, since, watch)

          {:read, ws} when is_map_key(since, ws) ->
            {watch, links, at} = LinkWatch.read(watch, ws)
            send(agent, {:mtc_links, ws, links, at})
            forward_notices(agent, ref, since, watch)

          _ ->
            forward_notices(agent, ref, since, watch)
        end

      {:sync, from, sync_ref} ->
        send(from, {:mtc_synced, sync_ref})
        forward_notices(agent, ref, since, watch)

      {:DOWN, ^ref, :process, _, _} ->
        LinkWatch.detach()

      {:DOWN, _, :process, pid, _} ->
        case LinkWatch.down(watch, pid) do
          {watch, {:change, ws, key, state, at}} ->
            send(agent, {:mtc_link, ws, key, state, at})
            forward_notices(agent, ref, since, watch)

          {watch, :none} ->
            forward_notices(agent, ref, since, watch)
        end

      _other ->
        forward_notices(agent, ref, since, watch)
    end
  end

  @doc """
  Runs on the workstations' node (the agent asks it with `:erpc`): what the mailboxes of each
  of `ids` say (`read/1`), or `:absent` for one that does not run here (any more).
  """
  @spec read_local([term]) :: %{term => map | :absent}
  def read_local(ids), do: Map.new(ids, &{&1, read(&1)})

  @doc """
  What a workstation's mailboxes say, as the agent's model takes them (`Vws.Ops.MTConnect.Model`):
  `%{devices, commands, cmd_in, readings}`, or `:absent` when it does not run here.
  """
  @spec read(term) :: map | :absent
  def read(ws) do
    if Mailbox.exists?(ws) do
      devices =
        for loc <- 1..11, into: %{} do
          {value, _age} = Mailbox.get_device(ws, loc)
          {Mailbox.device_name(loc), value}
        end

      commands = for p <- Mailbox.partitions(), into: %{}, do: {p, Mailbox.command_status(ws, p)}
      cmd_in = for p <- Mailbox.partitions(), into: %{}, do: {p, elem(Mailbox.cmd_in(ws, p), 1)}

      readings =
        for {source, {value, _age}} <- Mailbox.readings(ws), into: %{}, do: {source, value}

      %{devices: devices, commands: commands, cmd_in: cmd_in, readings: readings}
    else
      :absent
    end
  rescue
    # the workstation stopped while we read it
    ArgumentError -> :absent
  end
end
