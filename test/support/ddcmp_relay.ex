defmodule Vws.Test.DDCMPRelay do
  @moduledoc """
  A line between two `Vws.Links.DDCMP` links, for tests: it listens on two loopback endpoints
  (`endpoints/1` → `{a, b}`), accepts one connection on each and forwards every chunk of bytes
  to the other side.

  Options: `seed` (for `:rand`, so a run's faults are reproducible), `drop` and `corrupt` — the
  chance, 0.0..1.0, that a chunk is lost, or has one random byte changed, on its way.

  It also watches the line: per direction it decodes the frames that arrive and records the
  largest number of data messages a side had outstanding — the data message's NUM minus the
  highest RESP that side had been sent so far. A side never sees acknowledgements earlier than
  the relay does, so this never exceeds the side's real count (`stats/1`).
  """

  use GenServer

  import Bitwise

  alias Vws.Links.DDCMP.Frame
  alias Vws.Links.DDCMP.Frame.{Control, Data}
  alias Vws.Links.Transport

  def start_link(opts \\ []), do: GenServer.start_link(__MODULE__, opts)

  def endpoints(relay), do: GenServer.call(relay, :endpoints)

  def stats(relay), do: GenServer.call(relay, :stats)

  @impl true
  def init(opts) do
    base = "ddcmp-relay-#{System.unique_integer([:positive])}"
    {:ok, la} = Transport.listen("loopback:#{base}-a")
    {:ok, lb} = Transport.listen("loopback:#{base}-b")

    seed = Keyword.get(opts, :seed, 1)

    state = %{
      listeners: %{a: la, b: lb},
      endpoints: {"loopback:#{base}-a", "loopback:#{base}-b"},
      conns: %{},
      rand: :rand.seed_s(:exsss, {seed, seed * 7 + 1, seed * 13 + 2}),
      drop: Keyword.get(opts, :drop, 0.0),
      corrupt: Keyword.get(opts, :corrupt, 0.0),
      decoders: %{a: Frame.new(), b: Frame.new()},
      acked: %{a: 0, b: 0},
      max_outstanding: %{a: 0, b: 0},
      dropped: 0,
      corrupted: 0,
      chunks: 0
    }

    send(self(), :accept)
    {:ok, state}
  end

  @impl true
  def handle_call(:endpoints, _from, state), do: {:reply, state.endpoints, state}

  def handle_call(:stats, _from, state) do
    {:reply, Map.take(state, [:max_outstanding, :dropped, :corrupted, :chunks]), state}
  end

  @impl true
  def handle_info(:accept, state) do
    state =
      Enum.reduce([:a, :b], state, fn side, state ->
        if Map.has_key?(state.conns, side) do
          state
        else
          case Transport.accept(state.listeners[side], 10) do
            {:ok, conn} ->
              :ok = Transport.activate(conn)
              put_in(state.conns[side], conn)

            {:error, %Vws.Links.Transport.Error{reason: :timeout}} ->
              state
          end
        end
      end)

    if map_size(state.conns) < 2, do: send(self(), :accept)
    {:noreply, state}
  end

  def handle_info(msg, state) do
    Enum.find_value(state.conns, {:noreply, state}, fn {side, conn} ->
      case Transport.handle_message(conn, msg) do
        {:data, bytes} ->
          :ok = Transport.activate(conn)
          {:noreply, forward(state, side, bytes)}

        :unknown ->
          nil

        _closed_or_error ->
          {:noreply, state}
      end
    end)
  end

  defp forward(state, from, bytes) do
    to = other(from)
    state = %{state | chunks: state.chunks + 1}
    {x, rand} = :rand.uniform_s(state.rand)
    state = %{state | rand: rand}

    cond do
      x < state.drop ->
        %{state | dropped: state.dropped + 1}

      x < state.drop + state.corrupt ->
        {at, rand} = :rand.uniform_s(byte_size(bytes), state.rand)
        {flip, rand} = :rand.uniform_s(255, rand)
        <<head::binary-size(at - 1), byte, tail::binary>> = bytes
        bytes = <<head::binary, bxor(byte, flip), tail::binary>>
        deliver(%{state | rand: rand, corrupted: state.corrupted + 1}, from, to, bytes)

      true ->
        deliver(state, from, to, bytes)
    end
  end

  defp deliver(state, from, to, bytes) do
    if conn = state.conns[to], do: Transport.send(conn, bytes)
    watch(state, from, bytes)
  end

  # Frames from `from` carry its data (checked against what `from` had acknowledged) and, in RESP,
  # acknowledgements of the other side's data.
  defp watch(state, from, bytes) do
    {items, decoder} = Frame.feed(state.decoders[from], bytes)
    state = put_in(state.decoders[from], decoder)

    Enum.reduce(items, state, fn
      %Data{num: num, resp: resp}, state ->
        outstanding = signed(num - state.acked[from])

        state = update_in(state.max_outstanding[from], &max(&1, outstanding))

        acknowledge(state, other(from), resp)

      %Control{type: type, rcvr: resp}, state when type in [:ack, :nak] ->
        acknowledge(state, other(from), resp)

      %Control{type: type}, state when type in [:strt, :stack] ->
        %{state | acked: %{a: 0, b: 0}}

      _other, state ->
        state
    end)
  end

  defp acknowledge(state, side, resp) do
    if signed(resp - state.acked[side]) > 0, do: put_in(state.acked[side], resp), else: state
  end

  defp signed(x) do
    d = band(x, 0xFF)
    if d >= 128, do: d - 256, else: d
  end

  defp other(:a), do: :b
  defp other(:b), do: :a
end
