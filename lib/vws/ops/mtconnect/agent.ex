defmodule Vws.Ops.MTConnect.Agent do
  @moduledoc """
  An MTConnect agent for every workstation of the cell (`Vws.CEC.Cell`: this node and every node
  connected to it): it records every change of a data item as an observation with a sequence
  number in a circular buffer, and answers the requests of the standard as MTConnect 2.5
  documents (`Vws.Ops.MTConnect.XML`, or JSON, `Vws.Ops.MTConnect.JSON`):

    * `probe/2` — `MTConnectDevices`, one `Device` per workstation (see `Vws.Ops.MTConnect.Model`);
    * `current/3` — `MTConnectStreams` with the latest observation of every data item, or the
      state at sequence `at`;
    * `sample/5` — `MTConnectStreams` with the observations from sequence `from`, at most
      `count` (a negative `count`: the last ones), up to sequence `to`;
    * `assets/2` — `MTConnectAssets` (this agent holds no assets: an empty, valid document).

  `path:` (an XPath, `Vws.Ops.MTConnect.Path`) and a device name limit what `current` and `sample`
  show. Every parameter out of its range is answered with an `MTConnectError` document as the
  reference agent (cppagent) answers it — see `docs/mtconnect.md` — never with data that
  ignores it.

  ## Recording: every change, when it happens

  The agent subscribes to each of its node's workstations' mailbox change notices
  (`Vws.CEC.Mailbox`, "Change notices": `Vws.CEC.Events` event `:mailbox`) and records each change of a
  data item the moment it is announced, with the time of the write: no transition between two
  reads is lost. Numeric samples (and the numbers in a message) are recorded only when they move
  by at least their deadband (`MINIMUM_DELTA` in the probe), so sensor noise does not flood the
  buffer. The links' connection states too: each link tells its changes in its telemetry
  (`[:vws, :sun_comm, :wc_connected | :wc_disconnected]`, `[:vws, :ddcmp, :state_change |
  :link_down]`, `[:vws, :dnc, :connected | :disconnected]`, `[:vws, :hpib, :connected |
  :disconnected]`), which the agent follows, recording each change at the time the link made it;
  a link process that dies is seen by its monitor, its connection `CLOSED` at once; a link seen
  for the first time (a restarted one's first word) has its workstation's links read again.

  Workstations on other nodes: a forwarder process on each such node (`Vws.Ops.MTConnect.Forwarder`) subscribes to their change
  notices (and their GE-2000 links' transfer progress, and their links' connection changes,
  `Vws.Ops.MTConnect.LinkWatch`), reads their mailboxes once and sends the agent that snapshot
  and then every change, so their transitions are recorded as they happen too; before each
  answer the agent asks each forwarder to confirm what it has sent, so an answer is never older
  than the request. Until a workstation's snapshot is in (or when its forwarder is gone), it is
  read as before: every `:interval` ms and before each answer, all of a node's in one call
  (`:erpc`). A node that does not answer within `:node_timeout` ms (default 1000) has every data
  item of its workstations made `UNAVAILABLE`.

  ## Buffer and checkpoints

  As the reference agent (`Vws.Ops.MTConnect.Buffer`, plain data the agent holds): the buffer holds the last `:buffer_size` observations (default
  131 072, cppagent's `BufferSize = 17`), and every `:checkpoint_frequency` observations
  (default 1000, cppagent's `CheckpointFrequency`) the state of every data item is kept, so
  that `current?at=N` is built from the checkpoint before `N` and the observations after it;
  `firstSequence` moves on as old observations fall out.

  When a workstation stops, every data item of its device becomes `UNAVAILABLE` and the agent's
  `DeviceRemoved` names it; the device stays in the probe and comes back to life if the
  workstation starts again. Before any workstation has run, the probe is a `NO_DEVICE` error.
  """
  use GenServer

  alias Vws.CEC.Mailbox
  alias Vws.Ops.MTConnect.{Buffer, Forwarder, LinkWatch, Model, Path, XML}

  @default_buffer 131_072
  @default_checkpoint 1000
  @default_count 100
  @asset_buffer 1024

  @type agent :: GenServer.server()
  @type answer :: {:ok, iodata} | {:error, 400 | 404, iodata}
  @type format :: :xml | :json

  @doc """
  Starts an agent. Options: `:name`, `:buffer_size` (131 072), `:checkpoint_frequency` (1000),
  `:interval` (ms, 250), `:node_timeout` (ms, 1000), `:workstations` (a function returning the
  ids of the workstations to serve, wherever in the cell they run; default every workstation of
  the cell), `:sender` (default the host name).
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts \\ []),
    do: GenServer.start_link(__MODULE__, opts, Keyword.take(opts, [:name]))

  @doc "The probe document (for one device, by name, or all). Options: `format:`."
  @spec probe(agent, String.t() | nil, keyword) :: answer
  def probe(agent, device \\ nil, opts \\ []),
    do: GenServer.call(agent, {:probe, device, opts})

  @doc "The current document (for one device, by name, or all). Options: `at:`, `path:`, `format:`."
  @spec current(agent, String.t() | nil, keyword) :: answer
  def current(agent, device \\ nil, opts \\ []),
    do: GenServer.call(agent, {:current, device, opts})

  @doc """
  The sample document: observations from sequence `from` (default `firstSequence`), at most
  `count` (default #{@default_count}; negative: the last ones before `from`, default the newest),
  for one device or all. Options: `to:`, `path:`, `format:`.
  """
  @spec sample(agent, integer | nil, integer | nil, String.t() | nil, keyword) :: answer
  def sample(agent, from, count, device \\ nil, opts \\ []),
    do: GenServer.call(agent, {:sample, from, count, device, opts})

  @doc """
  As `sample/5`, with the document's `nextSequence`: `{:ok, doc, next}` (for streaming).
  """
  @spec sample_page(agent, integer | nil, integer | nil, String.t() | nil, keyword) ::
          {:ok, iodata, pos_integer} | {:error, 400 | 404, iodata}
  def sample_page(agent, from, count, device \\ nil, opts \\ []),
    do: GenServer.call(agent, {:sample, from, count, device, [{:with_next, true} | opts]})

  @doc "The assets document (none here). Options: `format:`."
  @spec assets(agent, keyword) :: answer
  def assets(agent, opts \\ []), do: GenServer.call(agent, {:assets, opts})

  @doc "An error document with this agent's header (for requests the web layer refuses)."
  @spec error(agent, String.t(), String.t(), format) :: iodata
  def error(agent, code, text, format \\ :xml),
    do: GenServer.call(agent, {:error, code, text, format})

  @doc """
  Waits until the buffer holds an observation with sequence number at least `seq`, at most
  `timeout` ms: `:ok` or `:timeout`.
  """
  @spec await(agent, pos_integer, timeout) :: :ok | :timeout
  def await(agent, seq, timeout) do
    GenServer.call(agent, {:await, seq, timeout}, timeout + 5_000)
  end

  @doc "The buffer's sequence numbers: `%{first, last, next, size}`."
  @spec sequences(agent) :: map
  def sequences(agent), do: GenServer.call(agent, :sequences)

  ## Server

  @impl true
  def init(opts) do
    # its rendering is HTTP work: it yields to the workstations (Vws.Ops.Web.Server's moduledoc);
    # observations keep the time of the write, which the change notice carries
    Process.flag(:priority, :low)

    sender =
      Keyword.get_lazy(opts, :sender, fn ->
        {:ok, host} = :inet.gethostname()
        to_string(host)
      end)

    now = System.system_time(:microsecond)
    agent_device = Model.agent_device(sender)

    s = %{
      interval: Keyword.get(opts, :interval, 250),
      node_timeout: Keyword.get(opts, :node_timeout, 1_000),
      workstations: Keyword.get(opts, :workstations),
      unresponsive: MapSet.new(),
      sender: sender,
      instance_id: div(now, 1_000_000),
      model_change_time: XML.timestamp(now),
      agent_device: agent_device,
      devices: %{},
      order: [],
      gone: MapSet.new(),
      # per workstation: what is known of it (Model.facts) and how it is read
      facts: %{},
      local: %{},
      # other nodes' workstations: their nodes' forwarders, the ones asked to follow them, and
      # the ones whose snapshot came in (changes recorded as they come)
      forwarders: %{},
      following: %{},
      followed: MapSet.new(),
      items: Map.new(Model.items(agent_device), &{&1.id, &1}),
      buffer:
        Buffer.new(
          Keyword.get(opts, :buffer_size, @default_buffer),
          Keyword.get(opts, :checkpoint_frequency, @default_checkpoint)
        ),
      waiters: [],
      # documents rendered since the buffer last changed (see `rendered/3`)
      rendered: nil,
      # this node's workstations' links, told as they change (LinkWatch)
      link_watch: LinkWatch.new()
    }

    [avail, added, removed] = Model.items(agent_device)

    s =
      s
      |> record(avail, "AVAILABLE", now)
      |> record(added, "UNAVAILABLE", now)
      |> record(removed, "UNAVAILABLE", now)

    :ok = LinkWatch.attach()

    send(self(), :tick)
    {:ok, s}
  end

  @impl true
  def handle_info(:tick, s) do
    Process.send_after(self(), :tick, s.interval)
    {:noreply, refresh(s, :ask_all)}
  end

  def handle_info({:link_event, pid, event, meta, at}, s) do
    case LinkWatch.event(s.link_watch, pid, event, meta, at) do
      {:change, ws, key, state, at} ->
        {:noreply, link_changed(s, ws, key, state, at)}

      # a link not seen yet (restarted), or another process's (a simulator's end of a line):
      # the workstation's links are read again
      {:read, ws} ->
        if Map.has_key?(s.local, ws) and Map.has_key?(s.facts, ws) and
             not MapSet.member?(s.gone, ws),
           do: {:noreply, read_links(s, ws)},
           else: {:noreply, s}

      :none ->
        {:noreply, s}
    end
  end

  # another node's workstation: its forwarder tells its links' states and their changes
  def handle_info({:mtc_links, ws, links, at}, s) do
    if MapSet.member?(s.followed, ws) and Map.has_key?(s.facts, ws),
      do: {:noreply, observe_links(s, ws, links, at)},
      else: {:noreply, s}
  end

  def handle_info({:mtc_link, ws, key, state, at}, s) do
    if MapSet.member?(s.followed, ws),
      do: {:noreply, link_changed(s, ws, key, state, at)},
      else: {:noreply, s}
  end

  def handle_info({:vws_event, ws, :mailbox, {change, at}}, s),
    do: {:noreply, notice(s, ws, change, at)}

  # the GE-2000 link's transfer progress (Vws.Links.DNC, event :dnc_progress): the VMC's
  # dnc_transfer message
  def handle_info({:vws_event, ws, :dnc_progress, progress}, s),
    do:
      {:noreply,
       notice(s, ws, {:transfer, Model.transfer_text(progress)}, System.system_time(:microsecond))}

  def handle_info({:mtc_snapshot, ws, facts}, s) do
    if Map.get(s.following, ws) != nil and is_map(facts) and not MapSet.member?(s.gone, ws) do
      s = %{s | followed: MapSet.put(s.followed, ws)}
      {:noreply, observe_remote(s, ws, facts, System.system_time(:microsecond))}
    else
      {:noreply, s}
    end
  end

  # a link process died: its connection is closed; a forwarder ended (its node went away): its
  # workstations are read again until followed anew
  def handle_info({:DOWN, _ref, :process, pid, _reason}, s) do
    case Enum.find(s.forwarders, fn {_n, p} -> p == pid end) do
      nil ->
        case LinkWatch.down(s.link_watch, pid) do
          {watch, {:change, ws, key, state, at}} ->
            {:noreply, link_changed(%{s | link_watch: watch}, ws, key, state, at)}

          {_watch, :none} ->
            {:noreply, s}
        end

      {n, _} ->
        lost = for {ws, ^pid} <- s.following, do: ws

        {:noreply,
         %{
           s
           | forwarders: Map.delete(s.forwarders, n),
             following: Map.drop(s.following, lost),
             followed: MapSet.difference(s.followed, MapSet.new(lost))
         }}
    end
  end

  def handle_info({:await_timeout, ref}, s) do
    {mine, others} = Enum.split_with(s.waiters, &(elem(&1, 2) == ref))
    for {from, _seq, _ref} <- mine, do: GenServer.reply(from, :timeout)
    {:noreply, %{s | waiters: others}}
  end

  # (a late answer of a node is dropped by :erpc; nothing else is expected)
  def handle_info(_other, s), do: {:noreply, s}

  @impl true
  def terminate(_reason, _s) do
    LinkWatch.detach()
  end

  @impl true
  def handle_call({:probe, device, opts}, _from, s) do
    s = refresh(s)
    fmt = Keyword.get(opts, :format, :xml)

    reply =
      with {:ok, devices} <- devices(s, device, fmt) do
        if s.order == [],
          do: error(s, fmt, 404, "NO_DEVICE", "no workstation has run yet"),
          else: {:ok, render(fmt, :devices, header(s), devices)}
      end

    {:reply, reply, s}
  end

  def handle_call({:current, device, opts}, _from, s) do
    s = refresh(s)
    {reply, s} = rendered(s, {:current, device, opts}, fn -> current_answer(s, device, opts) end)
    {:reply, reply, s}
  end

  def handle_call({:sample, from, count, device, opts}, _from, s) do
    s = refresh(s)

    {reply, s} =
      rendered(s, {:sample, from, count, device, opts}, fn ->
        sample_answer(s, from, count, device, opts)
      end)

    {:reply, reply, s}
  end

  def handle_call({:assets, opts}, _from, s) do
    fmt = Keyword.get(opts, :format, :xml)
    count = Keyword.get(opts, :count)

    reply =
      if count != nil and count < 1 do
        range_error(s, fmt, "count", count, 1, @asset_buffer)
      else
        # this agent holds no assets: an empty document (for a device it knows)
        with {:ok, _} <- devices(s, Keyword.get(opts, :device), fmt),
             do: {:ok, render(fmt, :assets, header(s), [])}
      end

    {:reply, reply, s}
  end

  def handle_call({:error, code, text, fmt}, _from, s),
    do: {:reply, render(fmt, :error, header(s), {code, text}), s}

  def handle_call({:await, seq, timeout}, from, s) do
    if Buffer.next(s.buffer) > seq do
      {:reply, :ok, s}
    else
      ref = make_ref()
      Process.send_after(self(), {:await_timeout, ref}, timeout)
      {:noreply, %{s | waiters: [{from, seq, ref} | s.waiters]}}
    end
  end

  def handle_call(:sequences, _from, s) do
    s = refresh(s)
    {:reply, Buffer.sequences(s.buffer), s}
  end

  defp notice(s, ws, change, at) do
    follows? =
      case s.local do
        %{^ws => %{since: since}} -> at >= since
        _ -> MapSet.member?(s.followed, ws)
      end

    if follows? and Map.has_key?(s.facts, ws) do
      before = Map.fetch!(s.facts, ws)
      facts = apply_change(before, change)
      s = %{s | facts: Map.put(s.facts, ws, facts)}

      # a poll's changes touch a few items: those alone (Model.changed_values/3)
      case device_change(s, ws, change, before) do
        {:only, values} ->
          Enum.reduce(values, s, &record(&2, Map.fetch!(&2.items, elem(&1, 0)), elem(&1, 1), at))

        :all ->
          observe(s, ws, facts, at)
      end
    else
      s
    end
  end

  defp device_change(%{devices: devices, gone: gone}, ws, change, before) do
    if is_map_key(devices, ws) and not MapSet.member?(gone, ws),
      do: Model.changed_values(Map.fetch!(devices, ws), change, before),
      else: :all
  end

  # Before an answer: every change announced on another node before the request is in. Each
  # forwarder (of a node that answers) is asked to say so after what it has forwarded; its
  # notices then precede its answer in this mailbox, and are recorded here.
  defp sync_remote(s) do
    asked =
      for {n, pid} <- s.forwarders, n not in s.unresponsive do
        ref = make_ref()
        :ok = Forwarder.sync(pid, ref)
        ref
      end

    deadline = System.monotonic_time(:millisecond) + s.node_timeout
    Enum.each(asked, &await_synced(&1, deadline))
    drain(s)
  end

  defp await_synced(ref, deadline) do
    receive do
      {:mtc_synced, ^ref} -> :ok
    after
      max(deadline - System.monotonic_time(:millisecond), 0) -> :timeout
    end
  end

  defp drain(s) do
    receive do
      {:vws_event, ws, :mailbox, {change, at}} -> drain(notice(s, ws, change, at))
    after
      0 -> s
    end
  end

  ## Answers

  defp current_answer(s, device, opts) do
    fmt = Keyword.get(opts, :format, :xml)

    with {:ok, filter} <- filter(s, device, Keyword.get(opts, :path), fmt),
         {:ok, state} <- state_at(s, Keyword.get(opts, :at), fmt) do
      obs =
        for {id, {seq, value, ts}} <- state,
            filter == :all or MapSet.member?(filter, id),
            item = Map.fetch!(s.items, id),
            do: observation(item, seq, value, ts)

      obs = Enum.sort_by(obs, & &1.sequence)
      {:ok, render(fmt, :streams, streams_header(s, Buffer.next(s.buffer)), obs)}
    end
  end

  # A streams document is the same for the same request while nothing new is in the buffer and
  # the devices are as they were; only its creationTime would differ. Rendering one cost ~10 ms
  # of this process (one workstation), so a client asking again and again — a stream's first
  # document on every reconnection, 500 requests/s of many clients — held the node's cores
  # (issue 30). Kept at most @rendered_ms and for @rendered_max requests; anything new in the
  # buffer or the model starts afresh.
  @rendered_ms 1_000
  @rendered_max 64

  defp rendered(s, key, render) do
    now = System.monotonic_time(:millisecond)
    stamp = {Buffer.next(s.buffer), s.model_change_time, s.order}

    cache =
      case s.rendered do
        %{stamp: ^stamp, since: since} = cache when now - since < @rendered_ms -> cache
        _ -> %{stamp: stamp, since: now, docs: %{}}
      end

    case cache.docs do
      %{^key => reply} ->
        {reply, %{s | rendered: cache}}

      docs ->
        # one binary: an iolist of small binaries would be copied to the connection, whole
        reply = with {:ok, doc} <- render.(), do: {:ok, IO.iodata_to_binary(doc)}

        docs =
          if match?({:ok, _}, reply) and map_size(docs) < @rendered_max,
            do: Map.put(docs, key, reply),
            else: docs

        {reply, %{s | rendered: %{cache | docs: docs}}}
    end
  end

  # the state of every data item after sequence `at` (nil: now)
  defp state_at(s, nil, _fmt), do: {:ok, Buffer.current(s.buffer)}

  defp state_at(s, at, fmt) do
    with {:error, why} <- Buffer.state_at(s.buffer, at), do: buffer_error(s, fmt, why)
  end

  defp sample_answer(s, from, count, device, opts) do
    fmt = Keyword.get(opts, :format, :xml)

    with {:ok, filter} <- filter(s, device, Keyword.get(opts, :path), fmt),
         keep? = fn {_seq, id, _v, _ts} -> filter == :all or MapSet.member?(filter, id) end,
         {:ok, rows, next} <-
           Buffer.sample(s.buffer, from, count || @default_count, Keyword.get(opts, :to), keep?)
           |> or_buffer_error(s, fmt) do
      obs =
        for {seq, id, value, ts} <- rows, do: observation(Map.fetch!(s.items, id), seq, value, ts)

      doc = render(fmt, :streams, streams_header(s, next), obs)
      if Keyword.get(opts, :with_next), do: {:ok, doc, next}, else: {:ok, doc}
    end
  end

  defp or_buffer_error({:error, why}, s, fmt), do: buffer_error(s, fmt, why)
  defp or_buffer_error(ok, _s, _fmt), do: ok

  defp buffer_error(s, fmt, :zero_count),
    do: error(s, fmt, 400, "OUT_OF_RANGE", "'count' must not be zero(0)")

  defp buffer_error(s, fmt, {:out_of_range, param, value, min, max}),
    do: range_error(s, fmt, param, value, min, max)

  defp range_error(s, fmt, param, value, min, max) do
    error(
      s,
      fmt,
      400,
      "OUT_OF_RANGE",
      "'#{param}' must be between #{min} and #{max}, not #{value}"
    )
  end

  defp error(s, fmt, status, code, text),
    do: {:error, status, render(fmt, :error, header(s), {code, text})}

  # The data items a request may show: :all, or the ids of the device's and the path's.
  defp filter(s, device, path, fmt) do
    with {:ok, devices} <- devices(s, device, fmt) do
      cond do
        path != nil ->
          case Path.select(path, Path.tree(devices)) do
            {:ok, ids} ->
              {:ok, ids}

            {:error, why} ->
              error(s, fmt, 400, "INVALID_PATH", "the path could not be parsed: #{why}")
          end

        device != nil ->
          {:ok, MapSet.new(Enum.flat_map(devices, &Model.items/1), & &1.id)}

        true ->
          {:ok, :all}
      end
    end
  end

  defp devices(s, nil, _fmt),
    do: {:ok, [s.agent_device | Enum.map(s.order, &Map.fetch!(s.devices, &1))]}

  defp devices(s, name, fmt) do
    case Enum.find(
           [s.agent_device | Map.values(s.devices)],
           &(&1.name == name or &1.uuid == name)
         ) do
      nil -> error(s, fmt, 404, "NO_DEVICE", "no device named #{name}")
      d -> {:ok, [d]}
    end
  end

  defp observation(item, seq, value, ts),
    do: %{item: item, value: value, sequence: seq, timestamp: XML.timestamp(ts)}

  defp render(:xml, :devices, h, devices), do: XML.devices(h, devices)
  defp render(:xml, :streams, h, obs), do: XML.streams(h, obs)
  defp render(:xml, :assets, h, assets), do: XML.assets(h, assets)
  defp render(:xml, :error, h, {code, text}), do: XML.error(h, code, text)
  defp render(:json, :devices, h, devices), do: Vws.Ops.MTConnect.JSON.devices(h, devices)
  defp render(:json, :streams, h, obs), do: Vws.Ops.MTConnect.JSON.streams(h, obs)
  defp render(:json, :assets, h, assets), do: Vws.Ops.MTConnect.JSON.assets(h, assets)
  defp render(:json, :error, h, {code, text}), do: Vws.Ops.MTConnect.JSON.error(h, code, text)

  defp header(s) do
    %{
      creation_time: XML.timestamp(System.system_time(:microsecond)),
      sender: s.sender,
      instance_id: s.instance_id,
      buffer_size: Buffer.sequences(s.buffer).size,
      asset_buffer_size: @asset_buffer,
      model_change_time: s.model_change_time
    }
  end

  defp streams_header(s, next) do
    %{first: first, last: last} = Buffer.sequences(s.buffer)

    Map.merge(header(s), %{
      first_sequence: first,
      last_sequence: max(last, first),
      next_sequence: next
    })
  end

  ## Reading the workstations

  # `ask` is :ask_all on the periodic read, :skip_unresponsive before an answer.
  defp refresh(s, ask \\ :skip_unresponsive) do
    now = System.system_time(:microsecond)
    {running, s} = read_cell(s, ask)
    ids = MapSet.new(running, &elem(&1, 0))
    gone = Enum.reject(s.order, &(MapSet.member?(ids, &1) or MapSet.member?(s.gone, &1)))
    s = Enum.reduce(gone, s, &remove(&2, &1, now))

    s = if ask == :skip_unresponsive and s.forwarders != %{}, do: sync_remote(s), else: s

    Enum.reduce(running, s, fn
      {ws, :local, _node}, s ->
        follow_local(s, ws, now)

      {ws, :unreachable, _node}, s ->
        s = %{s | followed: MapSet.delete(s.followed, ws), following: Map.delete(s.following, ws)}
        observe_remote(s, ws, :unreachable, now)

      {ws, facts, n}, s ->
        if MapSet.member?(s.followed, ws),
          do: ensure_device(s, ws, now),
          else: s |> follow_remote(ws, n) |> observe_remote(ws, facts, now)
    end)
  end

  # A workstation of another node: its change notices reach the agent through a forwarder
  # process on that node (one per node), which subscribes, reads the mailboxes once, and sends
  # the agent that snapshot then every later change; until the snapshot is in, the workstation
  # is read as before.
  defp follow_remote(s, ws, n) do
    {pid, s} =
      case s.forwarders do
        %{^n => pid} ->
          {pid, s}

        _ ->
          pid = Forwarder.start(n, self())
          {pid, %{s | forwarders: Map.put(s.forwarders, n, pid)}}
      end

    case s.following do
      %{^ws => ^pid} ->
        s

      _ ->
        :ok = Forwarder.follow(pid, ws)
        %{s | following: Map.put(s.following, ws, pid)}
    end
  end

  # What every workstation served that runs now says: `[{id, :local | facts | :unreachable,
  # node}]`
  # in the cell's order; the other nodes' read on their node.
  defp read_cell(s, ask) do
    located = Vws.CEC.Cell.locations()

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
      for {n, ids} <- asked, do: {n, :erpc.send_request(n, Forwarder, :read_local, [ids])}

    here = Map.new(here, &{&1, if(Mailbox.exists?(&1), do: :local, else: :absent)})
    answered = for {n, req} <- requests, do: {n, receive_answer(req, deadline)}

    answers =
      for {_n, {:ok, theirs}} <- answered, reduce: here, do: (acc -> Map.merge(acc, theirs))

    unresponsive =
      MapSet.new(for({n, :error} <- answered, do: n) ++ Enum.map(skipped, &elem(&1, 0)))

    facts =
      for {ws, n} <- located,
          fact = if(n in unresponsive, do: :unreachable, else: Map.get(answers, ws, :absent)),
          fact != :absent,
          do: {ws, fact, n}

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

  # A workstation of this node: subscribed to its change notices, then read once; read again
  # whenever its mailboxes are new (it restarted between two ticks).
  defp follow_local(s, ws, now) do
    table =
      try do
        Mailbox.table(ws)
      rescue
        ArgumentError -> nil
      end

    case s.local do
      %{^ws => %{table: ^table}} when table != nil ->
        ensure_device(s, ws, now)

      _ when table == nil ->
        s

      _ ->
        if not Map.has_key?(s.local, ws) do
          :ok = Vws.CEC.Events.subscribe(ws, :mailbox)
          :ok = Vws.CEC.Events.subscribe(ws, :dnc_progress)
        end

        case Forwarder.read(ws) do
          :absent ->
            s

          facts ->
            old = Map.get(s.facts, ws, %{})
            facts = Map.merge(Map.take(old, [:program, :part_count, :links, :transfer]), facts)
            facts = Map.update(facts, :program, program(facts), &(program(facts) || &1))
            # its links read too, their processes watched from now on
            {watch, links, _at} = LinkWatch.read(s.link_watch, ws)
            facts = Map.put(facts, :links, links)
            s = %{s | local: Map.put(s.local, ws, %{table: table, since: now}), link_watch: watch}
            s = ensure_device(s, ws, now)
            observe(%{s | facts: Map.put(s.facts, ws, facts)}, ws, facts, now)
        end
    end
  end

  defp observe_remote(s, ws, :unreachable, now) do
    s = ensure_device(s, ws, now)
    record_values(s, ws, Model.observe(Map.fetch!(s.devices, ws), nil), now)
  end

  defp observe_remote(s, ws, facts, now) do
    old = Map.get(s.facts, ws, %{})
    facts = Map.merge(Map.take(old, [:program, :part_count, :links, :transfer]), facts)
    facts = Map.put(facts, :program, program(facts) || Map.get(old, :program))
    s = ensure_device(s, ws, now)
    observe(%{s | facts: Map.put(s.facts, ws, facts)}, ws, facts, now)
  end

  defp program(facts), do: Model.program(get_in(facts, [:cmd_in, :monarch]), nil)

  # One change notice applied to what is known of a workstation.
  @doc false
  def apply_change(facts, {:device, loc, value}),
    do: put_in(facts, [:devices, Mailbox.device_name(loc)], value)

  def apply_change(facts, {:readings, source, value}),
    do: Map.update(facts, :readings, %{source => value}, &Map.put(&1, source, value))

  def apply_change(facts, {:command, partition, number, status, text}) do
    facts =
      facts
      |> Map.update(
        :commands,
        %{partition => {number, status}},
        &Map.put(&1, partition, {number, status})
      )
      |> then(fn f ->
        if text,
          do: Map.update(f, :cmd_in, %{partition => text}, &Map.put(&1, partition, text)),
          else: f
      end)

    cmd = get_in(facts, [:cmd_in, partition])

    cond do
      partition == :monarch and status == :executing ->
        Map.put(facts, :program, Model.program(cmd, Map.get(facts, :program)))

      # a part is made when a cycle the VMC was started on ends DONE
      partition == :monarch and status == :done and is_binary(cmd) and cmd =~ ~r/^\s*CYCLE_START/ ->
        Map.update(facts, :part_count, 1, &(&1 + 1))

      true ->
        facts
    end
  end

  def apply_change(facts, {:transfer, text}), do: Map.put(facts, :transfer, text)

  def apply_change(facts, _other), do: facts

  defp ensure_device(s, ws, now) do
    case s.devices do
      %{^ws => d} ->
        if MapSet.member?(s.gone, ws),
          do:
            record(
              %{s | gone: MapSet.delete(s.gone, ws)},
              agent_item(s, "DEVICE_ADDED"),
              d.uuid,
              now
            ),
          else: s

      _ ->
        d = Model.device(ws)

        s = %{
          s
          | devices: Map.put(s.devices, ws, d),
            order: s.order ++ [ws],
            items: Map.merge(s.items, Map.new(Model.items(d), &{&1.id, &1})),
            model_change_time: XML.timestamp(now)
        }

        record(s, agent_item(s, "DEVICE_ADDED"), d.uuid, now)
    end
  end

  defp observe(s, ws, facts, now) do
    s = ensure_device(s, ws, now)
    record_values(s, ws, Model.observe(Map.fetch!(s.devices, ws), facts), now)
  end

  defp record_values(s, ws, values, now) do
    Enum.reduce(Model.items(Map.fetch!(s.devices, ws)), s, fn item, s ->
      record(s, item, Map.fetch!(values, item.id), now)
    end)
  end

  # A workstation's links read now: their states recorded, their processes known and monitored.
  defp read_links(s, ws) do
    {watch, links, at} = LinkWatch.read(s.link_watch, ws)
    observe_links(%{s | link_watch: watch}, ws, links, at)
  end

  defp observe_links(s, ws, links, at) do
    facts = Map.put(Map.fetch!(s.facts, ws), :links, links)
    observe(%{s | facts: Map.put(s.facts, ws, facts)}, ws, facts, at)
  end

  # One link's change, at the time the link made it.
  defp link_changed(s, ws, key, state, at) do
    with %{^ws => facts} <- s.facts,
         false <- MapSet.member?(s.gone, ws) do
      facts = Map.update(facts, :links, %{key => state}, &Map.put(&1, key, state))
      observe(%{s | facts: Map.put(s.facts, ws, facts)}, ws, facts, at)
    else
      _ -> s
    end
  end

  defp remove(s, ws, now) do
    device = Map.fetch!(s.devices, ws)
    s = record_values(s, ws, Model.observe(device, nil), now)
    s = record(s, agent_item(s, "DEVICE_REMOVED"), device.uuid, now)

    s =
      case s.local do
        %{^ws => _} ->
          Vws.CEC.Events.unsubscribe(ws, :mailbox)
          Vws.CEC.Events.unsubscribe(ws, :dnc_progress)
          %{s | local: Map.delete(s.local, ws), link_watch: LinkWatch.forget(s.link_watch, ws)}

        _ ->
          s
      end

    %{
      s
      | gone: MapSet.put(s.gone, ws),
        followed: MapSet.delete(s.followed, ws),
        following: Map.delete(s.following, ws)
    }
  end

  defp agent_item(s, type), do: Enum.find(Model.items(s.agent_device), &(&1.type == type))

  ## The buffer

  # an observation is recorded when the value changed (by at least a sample's deadband)
  defp record(s, item, value, now) do
    if Model.changed?(item, Buffer.latest(s.buffer, item.id), value),
      do: wake(%{s | buffer: Buffer.append(s.buffer, item.id, value, now)}),
      else: s
  end

  defp wake(%{waiters: []} = s), do: s

  defp wake(s) do
    next = Buffer.next(s.buffer)
    {ready, waiting} = Enum.split_with(s.waiters, fn {_from, seq, _ref} -> next > seq end)
    for {from, _seq, _ref} <- ready, do: GenServer.reply(from, :ok)
    %{s | waiters: waiting}
  end
end
