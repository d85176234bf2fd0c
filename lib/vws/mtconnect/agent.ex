defmodule Vws.MTConnect.Agent do
  @moduledoc """
  An MTConnect agent for every workstation of the cell (`Vws.Cell`: this node and every node
  connected to it): it reads their mailboxes, gives each change of a data item a sequence number
  and keeps the observations in a circular buffer, and answers the three requests of the standard
  as MTConnect 2.5 documents:

    * `probe/2` — `MTConnectDevices`, one `Device` per workstation (see `Vws.MTConnect.Model`);
    * `current/2` — `MTConnectStreams` with the latest observation of every data item;
    * `sample/4` — `MTConnectStreams` with the observations from sequence `from`, at most `count`.

  The mailboxes are read every `:interval` ms (default 250) and again before each answer, so a
  document is never older than the request. Each node reads its own workstations' mailboxes, all
  in one call per node (`:erpc`), the nodes in parallel. A node that does not answer within
  `:node_timeout` ms (default 1000) has every data item of its workstations made `UNAVAILABLE`
  — never its last values shown as if fresh — and the answer goes out without it; such a node is
  asked again by the periodic read, not before each answer, so that a node that hangs delays no
  request by more than one `:node_timeout`. The buffer holds the last `:buffer_size`
  observations (default 8192); `firstSequence` moves on as older ones fall out. A `from` outside
  `firstSequence..nextSequence` or a `count` outside `1..bufferSize` is answered with an
  `MTConnectError` document (`OUT_OF_RANGE`), an unknown device with `NO_DEVICE`.

  When a workstation stops, every data item of its device becomes `UNAVAILABLE` and the agent's
  `DeviceRemoved` names it; the device stays in the probe (as a machine that is switched off stays
  on the shop floor) and comes back to life if the workstation starts again. Before any
  workstation has run, the probe is a `NO_DEVICE` error: an MTConnect device list cannot be empty.
  `deviceModelChangeTime` says when a device was last added.
  """
  use GenServer

  alias Vws.Mailbox
  alias Vws.MTConnect.{Model, XML}

  @default_buffer 8192
  @default_count 100

  @type agent :: GenServer.server()
  @type answer :: {:ok, iodata} | {:error, 400 | 404, iodata}

  @doc """
  Starts an agent. Options: `:name`, `:buffer_size` (8192), `:interval` (ms, 250),
  `:node_timeout` (ms, 1000), `:workstations` (a function returning the ids of the workstations
  to serve, wherever in the cell they run; default every workstation of the cell), `:sender`
  (default the host name).
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts \\ []) do
    case Keyword.get(opts, :name) do
      nil -> GenServer.start_link(__MODULE__, opts)
      name -> GenServer.start_link(__MODULE__, opts, name: name)
    end
  end

  @doc "The probe document (for one device, by name, or all)."
  @spec probe(agent, String.t() | nil) :: answer
  def probe(agent, device \\ nil), do: GenServer.call(agent, {:probe, device})

  @doc "The current document (for one device, by name, or all)."
  @spec current(agent, String.t() | nil) :: answer
  def current(agent, device \\ nil), do: GenServer.call(agent, {:current, device})

  @doc """
  The sample document: observations from sequence `from` (default `firstSequence`), at most
  `count` (default #{@default_count}), for one device or all.
  """
  @spec sample(agent, integer | nil, integer | nil, String.t() | nil) :: answer
  def sample(agent, from, count, device \\ nil),
    do: GenServer.call(agent, {:sample, from, count, device})

  @doc "An error document with this agent's header (for requests the web layer cannot parse)."
  @spec error(agent, String.t(), String.t()) :: iodata
  def error(agent, code, text), do: GenServer.call(agent, {:error, code, text})

  @doc "The buffer's sequence numbers: `%{first, last, next, size}`."
  @spec sequences(agent) :: map
  def sequences(agent), do: GenServer.call(agent, :sequences)

  ## Server

  @impl true
  def init(opts) do
    sender =
      Keyword.get_lazy(opts, :sender, fn ->
        {:ok, host} = :inet.gethostname()
        to_string(host)
      end)

    now = System.system_time(:microsecond)

    s = %{
      buffer_size: Keyword.get(opts, :buffer_size, @default_buffer),
      interval: Keyword.get(opts, :interval, 250),
      node_timeout: Keyword.get(opts, :node_timeout, 1_000),
      workstations: Keyword.get(opts, :workstations),
      unresponsive: MapSet.new(),
      sender: sender,
      instance_id: div(now, 1_000_000),
      model_change_time: XML.timestamp(now),
      agent_device: Model.agent_device(sender),
      devices: %{},
      order: [],
      gone: MapSet.new(),
      programs: %{},
      current: %{},
      buffer: %{},
      first: 1,
      next: 1
    }

    [avail, added, removed] = Model.items(s.agent_device)

    s =
      s
      |> record(avail, "AVAILABLE", now)
      |> record(added, "UNAVAILABLE", now)
      |> record(removed, "UNAVAILABLE", now)

    send(self(), :tick)
    {:ok, s}
  end

  @impl true
  def handle_info(:tick, s) do
    Process.send_after(self(), :tick, s.interval)
    {:noreply, refresh(s, :ask_all)}
  end

  # (a late answer of a node is dropped by :erpc; nothing else is expected)
  def handle_info(_other, s), do: {:noreply, s}

  @impl true
  def handle_call({:probe, device}, _from, s) do
    s = refresh(s)

    reply =
      with {:ok, devices} <- devices(s, device) do
        if s.order == [],
          do: {:error, 404, XML.error(header(s), "NO_DEVICE", "no workstation has run yet")},
          else: {:ok, XML.devices(header(s), devices)}
      end

    {:reply, reply, s}
  end

  def handle_call({:current, device}, _from, s) do
    s = refresh(s)

    reply =
      with {:ok, devices} <- devices(s, device) do
        obs = for d <- devices, i <- Model.items(d), o = s.current[i.id], do: o
        {:ok, XML.streams(streams_header(s, s.next), obs)}
      end

    {:reply, reply, s}
  end

  def handle_call({:sample, from, count, device}, _from, s) do
    s = refresh(s)
    from = from || s.first
    count = count || @default_count

    reply =
      cond do
        from < s.first or from > s.next ->
          out_of_range(s, "'from' must be between #{s.first} and #{s.next}, not #{from}")

        count < 1 or count > s.buffer_size ->
          out_of_range(s, "'count' must be between 1 and #{s.buffer_size}, not #{count}")

        true ->
          with {:ok, _} <- devices(s, device) do
            {obs, next} = take(s, from, count, device)
            {:ok, XML.streams(streams_header(s, next), obs)}
          end
      end

    {:reply, reply, s}
  end

  def handle_call({:error, code, text}, _from, s),
    do: {:reply, XML.error(header(s), code, text), s}

  def handle_call(:sequences, _from, s) do
    s = refresh(s)
    {:reply, %{first: s.first, last: s.next - 1, next: s.next, size: s.buffer_size}, s}
  end

  defp out_of_range(s, text), do: {:error, 400, XML.error(header(s), "OUT_OF_RANGE", text)}

  defp devices(s, nil),
    do: {:ok, [s.agent_device | Enum.map(s.order, &Map.fetch!(s.devices, &1))]}

  defp devices(s, name) do
    case Enum.find([s.agent_device | Map.values(s.devices)], &(&1.name == name)) do
      nil -> {:error, 404, XML.error(header(s), "NO_DEVICE", "no device named #{name}")}
      d -> {:ok, [d]}
    end
  end

  # Observations from `from`, at most `count` (of `device` only, when given), and the sequence
  # number after the last one looked at.
  defp take(s, from, count, nil) do
    last = min(from + count - 1, s.next - 1)
    obs = for seq <- from..last//1, o = s.buffer[seq], do: o
    {obs, max(last + 1, from)}
  end

  defp take(s, from, count, device) do
    matching = for seq <- from..(s.next - 1)//1, o = s.buffer[seq], o.item.device == device, do: o

    case Enum.split(matching, count) do
      {taken, []} -> {taken, s.next}
      {taken, _more} -> {taken, List.last(taken).sequence + 1}
    end
  end

  defp header(s) do
    %{
      creation_time: XML.timestamp(System.system_time(:microsecond)),
      sender: s.sender,
      instance_id: s.instance_id,
      buffer_size: s.buffer_size,
      model_change_time: s.model_change_time
    }
  end

  defp streams_header(s, next) do
    Map.merge(header(s), %{
      first_sequence: s.first,
      last_sequence: max(s.next - 1, s.first),
      next_sequence: next
    })
  end

  ## Reading the mailboxes

  # `ask` is :ask_all on the periodic read, :skip_unresponsive before an answer.
  defp refresh(s, ask \\ :skip_unresponsive) do
    now = System.system_time(:microsecond)
    {running, s} = read_cell(s, ask)
    ids = MapSet.new(running, &elem(&1, 0))
    gone = Enum.reject(s.order, &(MapSet.member?(ids, &1) or MapSet.member?(s.gone, &1)))
    s = Enum.reduce(gone, s, &remove(&2, &1, now))
    Enum.reduce(running, s, fn {ws, facts}, s -> observe(s, ws, facts, now) end)
  end

  # What every workstation served that runs now says: `[{id, facts | :unreachable}]` in the
  # cell's order, read on each one's node.
  defp read_cell(s, ask) do
    located = Vws.Cell.locations()

    located =
      case s.workstations do
        nil ->
          located

        served ->
          served = MapSet.new(served.())
          Enum.filter(located, &MapSet.member?(served, elem(&1, 0)))
      end

    by_node = Enum.group_by(located, &elem(&1, 1), &elem(&1, 0))
    {here, remote} = Map.pop(by_node, node(), [])

    {asked, skipped} =
      Enum.split_with(remote, fn {n, _} -> ask == :ask_all or n not in s.unresponsive end)

    deadline = System.monotonic_time(:millisecond) + s.node_timeout

    requests =
      for {n, ids} <- asked, do: {n, :erpc.send_request(n, __MODULE__, :read_local, [ids])}

    # this node's own while the others read theirs
    here = read_local(here)
    answered = for {n, req} <- requests, do: {n, receive_answer(req, deadline)}

    answers =
      for {_n, {:ok, theirs}} <- answered, reduce: here, do: (acc -> Map.merge(acc, theirs))

    unresponsive =
      MapSet.new(for({n, :error} <- answered, do: n) ++ Enum.map(skipped, &elem(&1, 0)))

    facts =
      for {ws, n} <- located,
          fact = if(n in unresponsive, do: :unreachable, else: Map.get(answers, ws, :absent)),
          fact != :absent,
          do: {ws, fact}

    {facts, %{s | unresponsive: unresponsive}}
  end

  defp receive_answer(req, deadline) do
    timeout = max(deadline - System.monotonic_time(:millisecond), 0)

    case :erpc.receive_response(req, timeout) do
      %{} = answers -> {:ok, answers}
      _ -> :error
    end
  catch
    # timeout (the request is abandoned: a late answer is never delivered), noconnection, an
    # exception on that node (e.g. another version of this module)
    _, _ -> :error
  end

  @doc false
  # Runs on the workstations' node: what the mailboxes of each of `ids` say, or :absent for one
  # that does not run here (any more).
  @spec read_local([term]) :: %{term => map | :absent}
  def read_local(ids), do: Map.new(ids, &{&1, read(&1)})

  defp read(ws) do
    if Mailbox.exists?(ws) do
      devices =
        for loc <- 1..11, into: %{} do
          {value, _age} = Mailbox.get_device(ws, loc)
          {Mailbox.device_name(loc), value}
        end

      commands = for p <- Mailbox.partitions(), into: %{}, do: {p, Mailbox.command_status(ws, p)}

      {_n, monarch_text} = Mailbox.cmd_in(ws, :monarch)
      %{devices: devices, commands: commands, monarch_cmd: monarch_text}
    else
      :absent
    end
  rescue
    # the workstation stopped while we read it
    ArgumentError -> :absent
  end

  defp observe(s, ws, facts, now) do
    {device, s} =
      case s.devices do
        %{^ws => d} ->
          if MapSet.member?(s.gone, ws),
            do:
              {d,
               record(
                 %{s | gone: MapSet.delete(s.gone, ws)},
                 agent_item(s, "DEVICE_ADDED"),
                 d.uuid,
                 now
               )},
            else: {d, s}

        _ ->
          d = Model.device(ws)

          s = %{
            s
            | devices: Map.put(s.devices, ws, d),
              order: s.order ++ [ws],
              model_change_time: XML.timestamp(now)
          }

          {d, record(s, agent_item(s, "DEVICE_ADDED"), d.uuid, now)}
      end

    {values, s} =
      case facts do
        :unreachable ->
          {Model.observe(device, nil), s}

        %{} ->
          program = Model.program(facts.monarch_cmd, Map.get(s.programs, ws))
          facts = %{devices: facts.devices, commands: facts.commands, program: program}
          {Model.observe(device, facts), %{s | programs: Map.put(s.programs, ws, program)}}
      end

    Enum.reduce(Model.items(device), s, fn item, s ->
      record(s, item, Map.fetch!(values, item.id), now)
    end)
  end

  defp remove(s, ws, now) do
    device = Map.fetch!(s.devices, ws)
    s = Enum.reduce(Model.items(device), s, &record(&2, &1, "UNAVAILABLE", now))
    s = record(s, agent_item(s, "DEVICE_REMOVED"), device.uuid, now)
    %{s | gone: MapSet.put(s.gone, ws)}
  end

  defp agent_item(s, type), do: Enum.find(Model.items(s.agent_device), &(&1.type == type))

  defp record(s, item, value, now) do
    case s.current[item.id] do
      %{value: ^value} ->
        s

      _ ->
        append(s, %{item: item, value: value, sequence: s.next, timestamp: XML.timestamp(now)})
    end
  end

  defp append(s, obs) do
    s = %{
      s
      | buffer: Map.put(s.buffer, obs.sequence, obs),
        current: Map.put(s.current, obs.item.id, obs),
        next: s.next + 1
    }

    if map_size(s.buffer) > s.buffer_size,
      do: %{s | buffer: Map.delete(s.buffer, s.first), first: s.first + 1},
      else: s
  end
end
