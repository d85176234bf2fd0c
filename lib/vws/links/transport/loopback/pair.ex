defmodule Vws.Links.Transport.Loopback.Pair do
  @moduledoc false
  # One loopback connection: a single process holding both directions, so data order is the
  # order of `send` calls and nothing is copied more than once on its way.
  #
  # Each side has an owner (its controlling process, monitored), an inbox of bytes waiting for
  # the owner to `activate`, and a queue of writers blocked because that inbox is full (their
  # `send` gets its reply when the inbox drains below @high_water: back-pressure, so no buffer
  # grows without bound). A side closes when its owner calls `close` or dies; the other side
  # then receives everything already sent, and after it `{:vws_loopback_closed, ref}`. The
  # process stops when both sides are closed.

  use GenServer

  @high_water 1_048_576

  @type side :: :client | :server

  ## API (called through Vws.Links.Transport.Loopback)

  @spec start(term(), pid(), pid(), reference(), reference()) :: {:ok, pid()}
  def start(name, client_owner, server_owner, client_ref, server_ref) do
    GenServer.start(__MODULE__, {name, client_owner, server_owner, client_ref, server_ref})
  end

  def send(pair, side, data), do: call(pair, {:send, side, data}, {:error, :closed})
  def activate(pair, side), do: GenServer.cast(pair, {:activate, side})
  def close(pair, side), do: call(pair, {:close, side}, :ok)

  def controlling_process(pair, side, new_owner),
    do: call(pair, {:controlling_process, side, new_owner}, {:error, :closed})

  defp call(pair, request, if_gone) do
    GenServer.call(pair, request, :infinity)
  catch
    :exit, _ -> if_gone
  end

  ## Server

  @impl true
  def init({name, client_owner, server_owner, client_ref, server_ref}) do
    {:ok,
     %{
       name: name,
       client: new_side(client_owner, client_ref),
       server: new_side(server_owner, server_ref)
     }}
  end

  defp new_side(owner, ref) do
    %{
      owner: owner,
      monitor: Process.monitor(owner),
      ref: ref,
      active: false,
      inbox: [],
      inbox_size: 0,
      writers: :queue.new(),
      peer_closed: false,
      closed_sent: false,
      closed: false
    }
  end

  @impl true
  def handle_call({:send, side, data}, from, state) do
    to = other(side)
    receiver = state[to]

    cond do
      state[side].closed or receiver.closed ->
        {:reply, {:error, :closed}, state}

      receiver.inbox_size < @high_water and :queue.is_empty(receiver.writers) ->
        state = put_in(state[to], append(receiver, data))
        {:reply, :ok, deliver(state, to)}

      true ->
        receiver = %{receiver | writers: :queue.in({from, data}, receiver.writers)}
        {:noreply, put_in(state[to], receiver)}
    end
  end

  def handle_call({:close, side}, _from, state) do
    close_side(state, side, :ok)
  end

  def handle_call({:controlling_process, side, new_owner}, {caller, _}, state) do
    this = state[side]

    cond do
      this.closed ->
        {:reply, {:error, :closed}, state}

      this.owner != caller ->
        {:reply, {:error, :not_owner}, state}

      true ->
        Process.demonitor(this.monitor, [:flush])
        this = %{this | owner: new_owner, monitor: Process.monitor(new_owner)}
        {:reply, :ok, deliver(put_in(state[side], this), side)}
    end
  end

  @impl true
  def handle_cast({:activate, side}, state) do
    if state[side].closed do
      {:noreply, state}
    else
      {:noreply, deliver(put_in(state[side].active, true), side)}
    end
  end

  @impl true
  def handle_info({:DOWN, monitor, :process, _pid, _reason}, state) do
    cond do
      state.client.monitor == monitor -> close_side(state, :client, nil)
      state.server.monitor == monitor -> close_side(state, :server, nil)
      true -> {:noreply, state}
    end
  end

  def handle_info(_msg, state), do: {:noreply, state}

  ## Internals

  defp other(:client), do: :server
  defp other(:server), do: :client

  defp append(side, data) do
    %{side | inbox: [data | side.inbox], inbox_size: side.inbox_size + byte_size(data)}
  end

  # Sends the owner of `side` what is due to it, if it asked for it (active-once).
  defp deliver(state, side) do
    this = state[side]

    cond do
      not this.active or this.closed ->
        state

      this.inbox_size > 0 ->
        data = this.inbox |> Enum.reverse() |> IO.iodata_to_binary()
        Kernel.send(this.owner, {:vws_loopback, this.ref, data})
        this = admit_writers(%{this | active: false, inbox: [], inbox_size: 0})
        put_in(state[side], this)

      this.peer_closed and not this.closed_sent and :queue.is_empty(this.writers) ->
        Kernel.send(this.owner, {:vws_loopback_closed, this.ref})
        put_in(state[side], %{this | active: false, closed_sent: true})

      true ->
        state
    end
  end

  # Writers blocked on a full inbox go in, in order, while there is room.
  defp admit_writers(side) do
    if side.inbox_size < @high_water do
      case :queue.out(side.writers) do
        {{:value, {from, data}}, writers} ->
          GenServer.reply(from, :ok)
          admit_writers(append(%{side | writers: writers}, data))

        {:empty, _} ->
          side
      end
    else
      side
    end
  end

  defp close_side(state, side, reply) do
    this = state[side]

    if this.closed do
      reply(reply, state)
    else
      Process.demonitor(this.monitor, [:flush])
      # Writers into a closed side can never be read: their send fails, as on a reset socket.
      reject_writers(this.writers)

      this = %{
        this
        | closed: true,
          active: false,
          inbox: [],
          inbox_size: 0,
          writers: :queue.new(),
          monitor: nil
      }

      state = put_in(state[side], this)
      peer = other(side)

      if state[peer].closed do
        reject_writers(state[peer].writers)
        stop(reply, state)
      else
        reply(reply, deliver(put_in(state[peer].peer_closed, true), peer))
      end
    end
  end

  defp reject_writers(writers) do
    Enum.each(:queue.to_list(writers), fn {from, _} ->
      GenServer.reply(from, {:error, :closed})
    end)
  end

  defp reply(nil, state), do: {:noreply, state}
  defp reply(reply, state), do: {:reply, reply, state}

  defp stop(nil, state), do: {:stop, :normal, state}
  defp stop(reply, state), do: {:stop, :normal, reply, state}
end
