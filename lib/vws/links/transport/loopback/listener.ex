defmodule Vws.Links.Transport.Loopback.Listener do
  @moduledoc false
  # A loopback listener: registered in Vws.Registry under {:loopback, name}, it creates one
  # Pair per connect (or takes one its client created, :connect_pair) and hands the server side
  # to an acceptor. Until accepted, the listener
  # itself owns the server side (so a connect succeeds at once, like a TCP backlog, and a
  # listener that goes away takes its unaccepted connections with it). It stops when closed
  # or when the process that opened it exits.

  use GenServer

  alias Vws.Links.Transport.Loopback
  alias Vws.Links.Transport.Loopback.Pair

  @spec start(term(), pid(), pos_integer()) :: {:ok, pid()} | {:error, term()}
  def start(name, owner, backlog) do
    case GenServer.start(__MODULE__, {name, owner, backlog}, name: via(name)) do
      {:ok, pid} -> {:ok, pid}
      {:error, {:already_started, _}} -> {:error, :eaddrinuse}
      {:error, reason} -> {:error, reason}
    end
  end

  @spec whereis(term()) :: pid() | nil
  def whereis(name), do: Vws.Names.whereis(:loopback, name)

  defp via(name), do: Vws.Names.via(:loopback, name)

  @impl true
  def init({name, owner, backlog}) do
    {:ok,
     %{
       name: name,
       owner_monitor: Process.monitor(owner),
       backlog: backlog,
       pending: :queue.new(),
       waiters: :queue.new()
     }}
  end

  @impl true
  def handle_call({:connect, client}, _from, state) do
    if :queue.len(state.pending) >= state.backlog do
      {:reply, {:error, :econnrefused}, state}
    else
      client_ref = make_ref()
      server_ref = make_ref()
      {:ok, pair} = Pair.start(state.name, client, self(), client_ref, server_ref)
      client_handle = %Loopback{pair: pair, side: :client, ref: client_ref, name: state.name}
      server_handle = %Loopback{pair: pair, side: :server, ref: server_ref, name: state.name}
      state = %{state | pending: :queue.in(server_handle, state.pending)}
      {:reply, {:ok, client_handle}, serve_waiters(state)}
    end
  end

  # A pair started by the connecting side (possibly on another node, Vws.CEC.Cell.Connection): the
  # listener owns its server side until an acceptor takes it, as for a pair it started itself.
  def handle_call({:connect_pair, server_handle}, _from, state) do
    if :queue.len(state.pending) >= state.backlog do
      {:reply, {:error, :econnrefused}, state}
    else
      state = %{state | pending: :queue.in(server_handle, state.pending)}
      {:reply, :ok, serve_waiters(state)}
    end
  end

  def handle_call({:accept, timeout}, {pid, _} = from, state) do
    waiter = %{
      from: from,
      monitor: Process.monitor(pid),
      timer: timeout != :infinity && Process.send_after(self(), {:accept_timeout, from}, timeout)
    }

    {:noreply, serve_waiters(%{state | waiters: :queue.in(waiter, state.waiters)})}
  end

  def handle_call(:close, _from, state) do
    {:stop, :normal, :ok, state}
  end

  @impl true
  def handle_info({:accept_timeout, from}, state) do
    {timed_out, waiters} = take_waiter(state.waiters, &(&1.from == from))
    Enum.each(timed_out, &finish_waiter(&1, {:error, :timeout}))
    {:noreply, %{state | waiters: waiters}}
  end

  def handle_info({:DOWN, monitor, :process, _pid, _reason}, %{owner_monitor: monitor} = state) do
    {:stop, :normal, state}
  end

  def handle_info({:DOWN, monitor, :process, _pid, _reason}, state) do
    {gone, waiters} = take_waiter(state.waiters, &(&1.monitor == monitor))
    Enum.each(gone, &finish_waiter(&1, nil))
    {:noreply, %{state | waiters: waiters}}
  end

  def handle_info(_msg, state), do: {:noreply, state}

  @impl true
  def terminate(_reason, state) do
    Enum.each(:queue.to_list(state.waiters), &finish_waiter(&1, {:error, :closed}))
  end

  # Pairs pending connections with waiting acceptors, oldest first.
  defp serve_waiters(state) do
    with {{:value, handle}, pending} <- :queue.out(state.pending),
         {{:value, waiter}, waiters} <- :queue.out(state.waiters) do
      {acceptor, _} = waiter.from
      state = %{state | pending: pending}

      case Pair.controlling_process(handle.pair, :server, acceptor) do
        :ok ->
          finish_waiter(waiter, {:ok, handle})
          serve_waiters(%{state | waiters: waiters})

        {:error, _} ->
          # The pair is gone (its client quit before the accept); try the next one.
          serve_waiters(state)
      end
    else
      _ -> state
    end
  end

  defp take_waiter(waiters, match?) do
    {taken, kept} = Enum.split_with(:queue.to_list(waiters), match?)
    {taken, :queue.from_list(kept)}
  end

  defp finish_waiter(waiter, reply) do
    Process.demonitor(waiter.monitor, [:flush])
    if waiter.timer, do: Process.cancel_timer(waiter.timer)
    if reply, do: GenServer.reply(waiter.from, reply)
  end
end
