defmodule Vws.Links.Transport.Policy do
  @moduledoc """
  Who may connect to a listener of the node (SUN_COMM's WC port, the hydraulic controller's CEC
  port): an allow-list of addresses and networks, checked by the acceptor
  (`Vws.Links.Transport.start_acceptor/4`) before a connection reaches its owner.

  ## The rules (decisions)

    * **Default: loopback only.** Without an allow-list only `127.0.0.0/8` and `::1` may connect.
    * **Binding elsewhere needs an allow-list.** A TCP listener bound to an address that is not
      loopback (`0.0.0.0`, a LAN address) is refused unless an allow-list is given
      (`check_listen/2`); the list then replaces the default (add `127.0.0.1` to it to keep
      local clients).
    * A connection from an address not on the list is closed at once, before a byte is read,
      and logged (at most one line a second, with the number refused since the last one).
    * Transports without addresses (a tty, an in-memory loopback pair) are point-to-point: the
      list does not apply.

  An allow-list is written `10.0.0.5,10.0.0.0/24,::1` (commas or spaces; an address alone is
  a /32 or /128), as given to `--wc-allow` / `VWS_WC_ALLOW`.

      iex> {:ok, allow} = Vws.Links.Transport.Policy.parse_allow("10.0.0.5, 192.168.1.0/24")
      iex> Vws.Links.Transport.Policy.allowed?(allow, {192, 168, 1, 77})
      true
      iex> Vws.Links.Transport.Policy.allowed?(allow, {10, 0, 0, 6})
      false
      iex> Vws.Links.Transport.Policy.allowed?(:loopback, {127, 0, 0, 1})
      true
  """

  import Bitwise

  @typedoc "One network: an address tuple and a prefix length."
  @type network :: {:inet.ip_address(), non_neg_integer}
  @typedoc "`:loopback` (the default), or the networks that may connect."
  @type allow :: :loopback | [network]

  @loopback [{{127, 0, 0, 0}, 8}, {{0, 0, 0, 0, 0, 0, 0, 1}, 128}]

  @doc """
  Parses an allow-list: a string (`"10.0.0.5,10.0.0.0/24"`), a list of such strings or of
  `{address, prefix}` tuples, or `nil`/`""`/`:loopback` for the default.
  """
  @spec parse_allow(nil | String.t() | [String.t() | network] | :loopback) ::
          {:ok, allow} | {:error, String.t()}
  def parse_allow(nil), do: {:ok, :loopback}
  def parse_allow(:loopback), do: {:ok, :loopback}

  def parse_allow(text) when is_binary(text) do
    case String.split(text, [",", " ", "\t", "\n"], trim: true) do
      [] -> {:ok, :loopback}
      entries -> parse_allow(entries)
    end
  end

  def parse_allow(entries) when is_list(entries) do
    Enum.reduce_while(entries, {:ok, []}, fn entry, {:ok, acc} ->
      case network(entry) do
        {:ok, net} -> {:cont, {:ok, acc ++ [net]}}
        :error -> {:halt, {:error, "#{inspect(entry)} is not an address or address/prefix"}}
      end
    end)
  end

  @doc "Like `parse_allow/1`, raising `ArgumentError` on a malformed list."
  @spec parse_allow!(term) :: allow
  def parse_allow!(text) do
    case parse_allow(text) do
      {:ok, allow} -> allow
      {:error, message} -> raise ArgumentError, "bad allow-list: " <> message
    end
  end

  defp network({ip, bits} = net) when is_tuple(ip) and is_integer(bits) do
    if bits >= 0 and bits <= width(ip), do: {:ok, net}, else: :error
  end

  defp network(text) when is_binary(text) do
    {address, bits} =
      case String.split(String.trim(text), "/", parts: 2) do
        [a] -> {a, nil}
        [a, b] -> {a, Integer.parse(b)}
      end

    with {:ok, ip} <- :inet.parse_strict_address(String.to_charlist(address)) do
      case bits do
        nil -> {:ok, {ip, width(ip)}}
        {n, ""} -> network({ip, n})
        _ -> :error
      end
    else
      _ -> :error
    end
  end

  defp network(_), do: :error

  @doc "Whether `ip` may connect under `allow`."
  @spec allowed?(allow, :inet.ip_address()) :: boolean
  def allowed?(:loopback, ip), do: allowed?(@loopback, ip)

  def allowed?(networks, ip) when is_list(networks) do
    ip = unmap(ip)
    Enum.any?(networks, fn {net, bits} -> same_network?(net, ip, bits) end)
  end

  @doc "Whether an address is a loopback address."
  @spec loopback?(:inet.ip_address()) :: boolean
  def loopback?(ip), do: allowed?(@loopback, ip)

  @doc """
  `:ok` when a listener on `endpoint` may start under `allow`: any non-TCP endpoint, a TCP one
  bound to loopback, or one bound elsewhere with an explicit allow-list. Otherwise an error
  saying what to do.
  """
  @spec check_listen(Vws.Links.Endpoint.t() | String.t(), allow) :: :ok | {:error, String.t()}
  def check_listen(endpoint, allow) when is_binary(endpoint),
    do: check_listen(Vws.Links.Endpoint.parse!(endpoint), allow)

  def check_listen(%Vws.Links.Endpoint{kind: :tcp, host: host} = endpoint, :loopback) do
    case bind_ip(host) do
      {:ok, ip} ->
        if loopback?(ip),
          do: :ok,
          else:
            {:error,
             "#{endpoint} is not a loopback address: listening there needs an allow-list of " <>
               "the addresses that may connect (--wc-allow / VWS_WC_ALLOW, e.g. 10.0.0.5,10.0.0.0/24)"}

      :error ->
        {:error, "cannot resolve the address to listen on in #{endpoint}"}
    end
  end

  def check_listen(_endpoint, _allow), do: :ok

  defp bind_ip(host) do
    host = to_charlist(host)

    case :inet.parse_address(host) do
      {:ok, ip} ->
        {:ok, ip}

      {:error, _} ->
        case :inet.getaddr(host, :inet) do
          {:ok, ip} -> {:ok, ip}
          {:error, _} -> :error
        end
    end
  end

  @doc "A printable allow-list."
  @spec describe(allow) :: String.t()
  def describe(:loopback), do: "loopback only"

  def describe(networks),
    do: Enum.map_join(networks, ",", fn {ip, bits} -> "#{:inet.ntoa(ip)}/#{bits}" end)

  # ::ffff:a.b.c.d (an IPv4 peer on a dual-stack socket) is a.b.c.d
  defp unmap({0, 0, 0, 0, 0, 0xFFFF, ab, cd}), do: {ab >>> 8, ab &&& 255, cd >>> 8, cd &&& 255}
  defp unmap(ip), do: ip

  defp width(ip) when tuple_size(ip) == 4, do: 32
  defp width(ip) when tuple_size(ip) == 8, do: 128

  defp same_network?(net, ip, bits) when tuple_size(net) == tuple_size(ip) do
    width = width(ip)
    shift = width - bits
    to_int(net) >>> shift == to_int(ip) >>> shift
  end

  defp same_network?(_net, _ip, _bits), do: false

  defp to_int(ip) when tuple_size(ip) == 4,
    do: ip |> Tuple.to_list() |> Enum.reduce(0, &(&2 <<< 8 ||| &1))

  defp to_int(ip) when tuple_size(ip) == 8,
    do: ip |> Tuple.to_list() |> Enum.reduce(0, &(&2 <<< 16 ||| &1))
end
