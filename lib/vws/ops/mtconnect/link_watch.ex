defmodule Vws.Ops.MTConnect.LinkWatch do
  @moduledoc false
  # The connection states of the links of a node's workstations, as they change — for the
  # MTConnect agent (this node's workstations) and its forwarders (another node's). A process
  # that keeps a watch calls `attach/0` once: each link then tells it of its changes through its
  # telemetry, in the link's own process, with the time it happened —
  #
  #     {:link_event, pid, event, meta, at}
  #
  # which `event/5` turns into a change of one link (or a call to read the workstation's links
  # again: a process not known yet, e.g. a restarted link's first word). `read/2` reads a
  # workstation's links and monitors their processes; `down/2` turns a monitored process's
  # :DOWN into its link CLOSED. A link's word older than the last reading of its workstation's
  # links is in that reading, and dropped.
  #
  # Keys: :wc (SUN_COMM), :val, :dnc, :daq1, :hydraulic; states "ESTABLISHED", "LISTEN",
  # "CLOSED" (MTConnect's ConnectionStatus).

  defstruct pids: %{}, read_at: %{}

  @type t :: %__MODULE__{pids: %{pid => {term, atom}}, read_at: %{term => integer}}
  @type change :: {:change, term, atom, String.t(), integer}

  @events [
    [:vws, :sun_comm, :wc_connected],
    [:vws, :sun_comm, :wc_disconnected],
    [:vws, :ddcmp, :state_change],
    [:vws, :ddcmp, :link_down],
    [:vws, :dnc, :connected],
    [:vws, :dnc, :disconnected],
    [:vws, :hpib, :connected],
    [:vws, :hpib, :disconnected]
  ]

  @doc false
  def new, do: %__MODULE__{}

  @doc false
  # The calling process is told of every link's change of this node (until detach/1 or its end).
  def attach(owner \\ self()),
    do: Vws.Telemetry.attach_many({__MODULE__, owner}, @events, &__MODULE__.handle/4, owner)

  @doc false
  def detach(owner \\ self()), do: Vws.Telemetry.detach({__MODULE__, owner})

  @doc false
  # The telemetry handler, in the link's process: tells the watcher, with the time.
  def handle(event, _measurements, meta, owner) do
    send(owner, {:link_event, self(), List.last(event), meta, System.system_time(:microsecond)})
    :ok
  end

  @doc false
  # A workstation's links read now: `{watch, states, at}`, their processes monitored.
  @spec read(t, term) :: {t, %{atom => String.t()}, integer}
  def read(%__MODULE__{} = w, ws) do
    at = System.system_time(:microsecond)
    {states, pids} = links_of(ws)

    new =
      for {pid, key} <- pids, not Map.has_key?(w.pids, pid), into: %{} do
        Process.monitor(pid)
        {pid, {ws, key}}
      end

    {%{w | pids: Map.merge(w.pids, new), read_at: Map.put(w.read_at, ws, at)}, states, at}
  end

  @doc false
  # A `{:link_event, …}` message: the change it makes, the workstation whose links are to be read
  # again (a process not known: `ws` from the event, which may not be watched), or nothing.
  @spec event(t, pid, atom, map, integer) :: change | {:read, term} | :none
  def event(%__MODULE__{} = w, pid, event, meta, at) do
    case w.pids do
      %{^pid => {ws, key}} ->
        case state(key, event, meta) do
          nil ->
            :none

          state ->
            if at >= Map.get(w.read_at, ws, 0), do: {:change, ws, key, state, at}, else: :none
        end

      _ ->
        case meta[:workstation] || meta[:bus] do
          nil -> :none
          ws -> {:read, ws}
        end
    end
  end

  @doc false
  # A monitored process ended: `{watch, {:change, ws, key, "CLOSED", now}}`, or `{watch, :none}`
  # for a process that is not a link's.
  @spec down(t, pid) :: {t, change | :none}
  def down(%__MODULE__{} = w, pid) do
    case Map.pop(w.pids, pid) do
      {{ws, key}, pids} ->
        {%{w | pids: pids}, {:change, ws, key, "CLOSED", System.system_time(:microsecond)}}

      {nil, _} ->
        {w, :none}
    end
  end

  @doc false
  # The workstation is no longer watched.
  @spec forget(t, term) :: t
  def forget(%__MODULE__{} = w, ws) do
    %{
      w
      | pids: Map.reject(w.pids, fn {_pid, {id, _}} -> id == ws end),
        read_at: Map.delete(w.read_at, ws)
    }
  end

  # The connection a link's telemetry event says it has (nil: the event does not say).
  defp state(:wc, :wc_connected, _meta), do: "ESTABLISHED"
  defp state(:wc, :wc_disconnected, _meta), do: "LISTEN"
  defp state(:val, :state_change, %{to: :running}), do: "ESTABLISHED"
  defp state(:val, :state_change, _meta), do: "CLOSED"
  defp state(:val, :link_down, _meta), do: "CLOSED"
  defp state(_key, :connected, _meta), do: "ESTABLISHED"
  defp state(_key, :disconnected, _meta), do: "CLOSED"
  defp state(_key, _event, _meta), do: nil

  # `{states, [{pid, key}]}` for the links a workstation has: `%{wc | val | dnc | daq1 |
  # hydraulic => "ESTABLISHED" | "LISTEN" | "CLOSED"}` and the processes that have them (SUN_COMM
  # for the WC link), from its link rows (`Vws.Ops.Inspect.link_rows/1`).
  defp links_of(ws) do
    keyed =
      for row <- Vws.Ops.Inspect.link_rows(ws), key = link_key(row), key != nil, do: {key, row}

    sun_comm = Vws.CEC.Workstation.whereis(ws, :sun_comm)

    pids =
      for({key, %{pid: pid}} <- keyed, is_pid(pid), do: {pid, key}) ++
        if(is_pid(sun_comm), do: [{sun_comm, :wc}], else: [])

    states = Map.new(keyed, fn {key, row} -> {key, connection(key, row.state)} end)
    {Map.put(states, :wc, wc_state(ws)), pids}
  rescue
    _ -> {%{}, []}
  catch
    :exit, _ -> {%{}, []}
  end

  defp wc_state(ws) do
    case Vws.Ops.Inspect.wc_info(ws) do
      %{peer: peer} when peer != nil -> "ESTABLISHED"
      %{listening: listening} when listening != nil -> "LISTEN"
      _ -> "CLOSED"
    end
  end

  defp link_key(%{id: :val}), do: :val
  defp link_key(%{id: :ge2000}), do: :dnc
  defp link_key(%{id: {Vws.Links.HPIB, _, _}, info: %{device: "DAQ #1"}}), do: :daq1
  defp link_key(%{id: {Vws.Links.HPIB, _, _}, info: %{device: "HYDRAULIC" <> _}}), do: :hydraulic
  defp link_key(_row), do: nil

  # the VAL II layer: {lun2, activity}, lun2 :down when its DDCMP link is not running
  defp connection(:val, {:down, _}), do: "CLOSED"
  defp connection(:val, {_lun2, _activity}), do: "ESTABLISHED"
  defp connection(:dnc, state) when state in [:disconnected, :down], do: "CLOSED"
  defp connection(:dnc, state) when is_atom(state), do: "ESTABLISHED"
  defp connection(_hpib, state) when state in [:ready, :busy], do: "ESTABLISHED"
  defp connection(_key, _state), do: "CLOSED"
end
