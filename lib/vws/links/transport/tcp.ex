defmodule Vws.Links.Transport.TCP do
  @moduledoc """
  `Vws.Links.Transport` over TCP (`:gen_tcp`), client and listener: simulators, terminal servers
  (ser2net, Moxa in raw TCP mode) and LAN instruments.

  Sockets are binary, raw (no packet framing), `nodelay`, and passive until the first
  `activate/1`; one delivery holds up to 64 KB. The handle is the `:gen_tcp` socket; the owner
  receives the standard `{:tcp, socket, data}`, `{:tcp_closed, socket}` and
  `{:tcp_error, socket, reason}` messages.

  **Armed for eight deliveries at a time** (`active: 8`), not one: re-arming a socket after every
  delivery (`active: :once`) is a call into the driver and a change of the kernel's poll set each
  time, and for a VWS_STATUS poll (one request, an answer in one or two deliveries) that was about
  15 µs of CPU of an exchange's 55–70 (a loopback ping-pong of 20,000 exchanges on this 2-core
  VM, active-once against active-N). `activate/1` re-arms only when the socket has gone passive:
  the driver says so with `{:tcp_passive, socket}`, which `handle_message/2` gives as
  `{:data, ""}` — no bytes, and the owner's `activate/1` that follows every data arms the next
  eight. What arrives unread is bounded all the same: at most eight
  deliveries (512 KB) wait in the owner's mailbox before it has read them. Whether a socket is
  armed is kept in the owner's process dictionary (a socket handed to another process is armed
  again by its first `activate/1`; the count adds up in the driver, and stays bounded).
  `activate_once/1` arms one delivery alone, for an owner that must hold its sender back after
  each (a simulated line's pump).

  Options: `connect/2` takes `timeout` (ms, default 5000); `listen/2` takes `ip` (an address
  tuple or string, overriding the endpoint's host), `backlog` (default 128) and `send_timeout`
  (ms; default none): a send to an accepted connection that the peer has not made room for
  within it fails `{:error, :timeout}` and closes the connection (`send_timeout_close`), so a
  peer that never reads cannot block its owner for longer.
  """

  @behaviour Vws.Links.Transport.Behaviour

  import Kernel, except: [send: 2]

  alias Vws.Links.Endpoint

  # `buffer` is the most one delivery can hold; the driver's default (1460) would cut a burst
  # into a message per TCP segment.
  @socket_opts [:binary, packet: :raw, active: false, nodelay: true, buffer: 65_536]
  @connect_timeout 5000

  @impl true
  def connect(%Endpoint{kind: :tcp, host: host, port: port}, opts) do
    :gen_tcp.connect(host, port, @socket_opts, Keyword.get(opts, :timeout, @connect_timeout))
  end

  @impl true
  def listen(%Endpoint{kind: :tcp, host: host, port: port}, opts) do
    with {:ok, ip} <- bind_address(Keyword.get(opts, :ip, host)) do
      send_timeout =
        case Keyword.get(opts, :send_timeout) do
          nil -> []
          ms -> [send_timeout: ms, send_timeout_close: true]
        end

      :gen_tcp.listen(
        port,
        @socket_opts ++
          [reuseaddr: true, ip: ip, backlog: Keyword.get(opts, :backlog, 128)] ++ send_timeout
      )
    end
  end

  defp bind_address(ip) when is_tuple(ip), do: {:ok, ip}
  defp bind_address(ip) when is_binary(ip), do: bind_address(String.to_charlist(ip))

  defp bind_address(ip) when is_list(ip) do
    case :inet.parse_address(ip) do
      {:ok, ip} -> {:ok, ip}
      {:error, _} -> :inet.getaddr(ip, :inet)
    end
  end

  @impl true
  def listener_endpoint(listen_socket) do
    {:ok, {ip, port}} = :inet.sockname(listen_socket)
    %Endpoint{kind: :tcp, host: :inet.ntoa(ip), port: port}
  end

  @impl true
  def accept(listen_socket, timeout), do: :gen_tcp.accept(listen_socket, timeout)

  @impl true
  def close_listener(listen_socket), do: :gen_tcp.close(listen_socket)

  @impl true
  def send(socket, data), do: :gen_tcp.send(socket, data)

  @impl true
  def close(socket) do
    Process.delete({__MODULE__, socket})
    :gen_tcp.close(socket)
  end

  @impl true
  def controlling_process(socket, pid), do: :gen_tcp.controlling_process(socket, pid)

  # deliveries armed at a time (the moduledoc)
  @armed 8

  # An error here means the socket is closed; the owner has had (or will have) the close message.
  @impl true
  def activate(socket) do
    case Process.get({__MODULE__, socket}) do
      true ->
        :ok

      nil ->
        _ = :inet.setopts(socket, active: @armed)
        Process.put({__MODULE__, socket}, true)
        :ok
    end
  end

  # One delivery alone: for an owner whose bound is one (the moduledoc of Vws.Links.Transport).
  @impl true
  def activate_once(socket) do
    _ = :inet.setopts(socket, active: :once)
    :ok
  end

  @impl true
  def handle_message(socket, {:tcp, socket, data}), do: {:data, data}

  # the armed deliveries are used up: no bytes, and the owner's activate/1 arms the next ones
  def handle_message(socket, {:tcp_passive, socket}) do
    Process.delete({__MODULE__, socket})
    {:data, ""}
  end

  def handle_message(socket, {:tcp_closed, socket}) do
    Process.delete({__MODULE__, socket})
    :closed
  end

  def handle_message(socket, {:tcp_error, socket, reason}) do
    Process.delete({__MODULE__, socket})
    {:error, reason}
  end

  def handle_message(_socket, _msg), do: :unknown

  @impl true
  def peer(socket) do
    case :inet.peername(socket) do
      {:ok, {ip, port}} -> "tcp://#{:inet.ntoa(ip)}:#{port}"
      {:error, _} -> "tcp://(closed)"
    end
  end
end
