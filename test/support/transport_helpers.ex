defmodule Vws.TransportHelpers do
  @moduledoc """
  Receiving from a `Vws.Links.Transport` connection in tests, the way a driver would: activate, take
  one message, classify it with `Vws.Links.Transport.handle_message/2`.
  """

  import ExUnit.Assertions

  alias Vws.Links.Transport

  @doc "Activates and collects messages until `size` bytes have arrived; returns them."
  def recv_exactly(conn, size, timeout \\ 5000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    collect(conn, size, deadline, [])
  end

  defp collect(_conn, remaining, _deadline, acc) when remaining <= 0,
    do: IO.iodata_to_binary(Enum.reverse(acc))

  defp collect(conn, remaining, deadline, acc) do
    :ok = Transport.activate(conn)

    case next(conn, max(deadline - System.monotonic_time(:millisecond), 0)) do
      {:data, data} -> collect(conn, remaining - byte_size(data), deadline, [data | acc])
      other -> flunk("expected #{remaining} more bytes, got #{inspect(other)}")
    end
  end

  @doc """
  The classification of the first message in the mailbox that belongs to `conn`, waiting up to
  `timeout` ms for one (`:timeout`). Messages of other connections stay where they are, in order.
  """
  def next(conn, timeout \\ 5000) do
    id = identity(conn)

    receive do
      msg
      when is_tuple(msg) and tuple_size(msg) >= 2 and (elem(msg, 0) == id or elem(msg, 1) == id) ->
        case Transport.handle_message(conn, msg) do
          :unknown -> flunk("#{inspect(msg)} names #{inspect(conn)} but is not classified")
          result -> result
        end
    after
      timeout -> :timeout
    end
  end

  # What the messages of each transport carry to tell connections apart (test-only knowledge;
  # it lets `next/2` wait with a selective receive).
  defp identity(%{module: Vws.Links.Transport.TCP, handle: socket}), do: socket
  defp identity(%{module: Vws.Links.Transport.Loopback, handle: %{ref: ref}}), do: ref
  defp identity(%{module: Vws.Links.Transport.Serial, handle: %{port: port}}), do: port
  defp identity(%{module: Vws.Links.Transport.RFC2217, handle: %{pid: pid}}), do: pid

  @doc """
  Activates and expects the connection to be reported closed (after no bytes: a TCP socket's
  used-up deliveries, `{:data, ""}`, are passed over).
  """
  def assert_closed(conn, timeout \\ 5000) do
    :ok = Transport.activate(conn)

    case next(conn, timeout) do
      {:data, ""} -> assert_closed(conn, timeout)
      other -> assert other == :closed
    end
  end

  @doc "Polls `fun` until it returns truthy or `timeout` ms pass (then fails)."
  def wait_until(fun, timeout \\ 5000, message \\ "condition never became true") do
    deadline = System.monotonic_time(:millisecond) + timeout
    poll(fun, deadline, message)
  end

  defp poll(fun, deadline, message) do
    cond do
      fun.() ->
        :ok

      System.monotonic_time(:millisecond) > deadline ->
        flunk(message)

      true ->
        Process.sleep(5)
        poll(fun, deadline, message)
    end
  end
end
