defmodule Vws.Sim.Line.Session do
  @moduledoc false
  # One connection through a Vws.Sim.Line: takes the accepted client connection, dials the
  # target (retrying for connect_timeout ms: the far end may not be listening yet), and runs one
  # Pump per direction. The first pump to report ends the connection: both legs are closed, so
  # each end sees the link go down, and the session stops.

  use GenServer, restart: :temporary
  require Logger

  alias Vws.Sim.Line.{Counters, Pump}
  alias Vws.Links.Transport

  def start_link(args), do: GenServer.start_link(__MODULE__, args)

  @doc false
  def begin(session, conn), do: send(session, {:begin, conn})

  # Synchronous down to the pumps (see Pump.set_faults/3); gives up waiting after `timeout` ms
  # on a session still dialling or a pump stuck in a send.
  @doc false
  def set_faults(session, dir, opts, timeout) do
    GenServer.call(session, {:set_faults, dir, opts, timeout}, timeout)
  catch
    :exit, _ -> :ok
  end

  @doc false
  def disconnect(session), do: GenServer.cast(session, :disconnect)

  @impl true
  def init(args) do
    # The line stops its sessions with an exit signal; trapping it lets terminate/2 close both legs.
    Process.flag(:trap_exit, true)

    {:ok, Map.merge(args, %{client: nil, target_conn: nil, pumps: %{}})}
  end

  @impl true
  def handle_info({:begin, client}, state) do
    state = %{state | client: client}

    case dial(state.target, state.connect_timeout) do
      {:ok, target} ->
        {:noreply, start_pumps(%{state | target_conn: target})}

      {:error, reason} ->
        Logger.warning("line: cannot reach #{state.target}: #{inspect(reason)}")
        Counters.add(state.counters, :connect_failures)
        Transport.close(client)
        {:stop, :normal, %{state | client: nil}}
    end
  end

  # The destination of one direction went away: the other direction reads from that same
  # connection and will report its end once it has delivered what it holds.
  def handle_info({:pump, _pid, _dir, {:dest_failed, _reason}}, state), do: {:noreply, state}

  def handle_info({:pump, _pid, _dir, event}, state) do
    case event do
      {:cut, _why} -> Counters.add(state.counters, :disconnects)
      _eof_or_error -> Counters.add(state.counters, :closes)
    end

    {:stop, :normal, state}
  end

  # A pump that crashed: its connection cannot go on. (Other exits come from sockets' ports.)
  def handle_info({:EXIT, pid, reason}, state) do
    if pid in Map.values(state.pumps) do
      Logger.error("line: connection #{state.index} #{inspect(reason)}")
      Counters.add(state.counters, :closes)
      {:stop, :normal, state}
    else
      {:noreply, state}
    end
  end

  def handle_info(_msg, state), do: {:noreply, state}

  @impl true
  def handle_call({:set_faults, dir, opts, timeout}, _from, state) do
    state = put_in(state.faults[dir], Keyword.merge(state.faults[dir], opts))
    if pump = state.pumps[dir], do: Pump.set_faults(pump, opts, timeout)
    {:reply, :ok, state}
  end

  @impl true
  # (Never before {:begin, _}: the line sends that first, and the dial runs inside it.)
  def handle_cast(:disconnect, state) do
    Counters.add(state.counters, :disconnects)
    {:stop, :normal, state}
  end

  # Both legs close before the pumps go, so a pump blocked in a send returns.
  @impl true
  def terminate(_reason, state) do
    if state.client, do: Transport.close(state.client)
    if state.target_conn, do: Transport.close(state.target_conn)
    Enum.each(state.pumps, fn {_dir, pid} -> Process.exit(pid, :shutdown) end)
  end

  defp dial(target, timeout),
    do: dial_until(target, System.monotonic_time(:millisecond) + timeout)

  defp dial_until(target, deadline) do
    case Transport.connect(target) do
      {:ok, conn} ->
        {:ok, conn}

      {:error, reason} ->
        if System.monotonic_time(:millisecond) >= deadline do
          {:error, reason}
        else
          Process.sleep(20)
          dial_until(target, deadline)
        end
    end
  end

  defp start_pumps(state) do
    legs = %{
      to_target: {state.client, state.target_conn},
      to_client: {state.target_conn, state.client}
    }

    # where each direction tells the other how late its last bytes came out (see Pump)
    lateness = :atomics.new(6, signed: true)
    for i <- [2, 5], do: :atomics.put(lateness, i, -1)

    pumps =
      Map.new(legs, fn {dir, {source, dest}} ->
        {:ok, pid} =
          Pump.start_link(%{
            session: self(),
            dir: dir,
            source: source,
            dest: dest,
            counters: state.counters,
            max_queue: state.max_queue,
            faults: state.faults[dir],
            seed: {state.seed, state.index, dir},
            lateness: lateness,
            reply_slack: Map.get(state, :reply_slack, 0)
          })

        :ok = Transport.controlling_process(source, pid)
        {dir, pid}
      end)

    Enum.each(pumps, fn {_dir, pid} -> Pump.go(pid) end)
    %{state | pumps: pumps}
  end
end
