defmodule Vws.Links.Transport.RFC2217 do
  @moduledoc """
  `Vws.Links.Transport` to a serial port behind a terminal server that speaks RFC 2217
  (`rfc2217://host:port?baud=4800&parity=even&flow=xonxoff`; ser2net's `telnet(rfc2217)`
  accepter, Moxa and Digi device servers in RFC 2217 mode), client side only.

  ## Connecting

  `connect/2` dials the server and, before it returns, negotiates (`Vws.Codecs.RFC2217`):

    1. `WILL COM-PORT-OPTION`, `DO`/`WILL BINARY` (8-bit data, no NVT CR NUL), `DO`/`WILL SGA`;
       the server must answer `DO COM-PORT-OPTION` — a `DONT` is `{:error,
       :com_port_refused}`;
    2. the endpoint's settings: SET-BAUDRATE, SET-DATASIZE, SET-PARITY, SET-STOPSIZE, SET-CONTROL
       (flow `none` 1, `xonxoff` 2, `rtscts` 3), and SET-LINESTATE-MASK / SET-MODEMSTATE-MASK so
       that the server tells line errors and modem-line changes;
    3. each setting's answer (101–105) must be the value asked: another one is
       `{:error, {:setting_refused, key, asked, answered}}` (say, a port that cannot do 7 data
       bits, or RTS/CTS).

  Everything must be done within `timeout` (option, default 5 000 ms): else `{:error,
  :negotiation_timeout}`. Serial data that arrives meanwhile is kept for the owner.

  ## The connection

  A process (linked to nobody, monitoring its owner) holds the socket and the telnet decoder,
  so that an IAC split over two TCP segments is read right. Data is sent IAC-doubled straight
  on the socket; received data is un-doubled and delivered active-once as
  `{:rfc2217, pid, {:data, bytes}}` (`:closed`, `{:error, reason}` at the end). Line-state
  notifications (overrun, parity, framing error, break) are logged and counted as the telemetry
  event `[:vws, :rfc2217, :line_state]`; modem-state notifications (carrier, DSR, CTS) are kept
  (`line_state/1`) and logged when they change. Negotiation the server starts for any other
  option is refused (`WONT`/`DONT`).
  """
  @behaviour Vws.Links.Transport.Behaviour

  use GenServer
  require Logger

  import Kernel, except: [send: 2]

  alias Vws.Codecs.RFC2217, as: Telnet
  alias Vws.Links.Endpoint

  @binary 0
  @sga 3
  @com_port 44
  @connect_timeout 5_000

  defstruct [:pid, :socket, :endpoint]

  @type t :: %__MODULE__{pid: pid, socket: port, endpoint: Endpoint.t()}

  @impl Vws.Links.Transport.Behaviour
  def connect(%Endpoint{kind: :rfc2217} = endpoint, opts) do
    timeout = Keyword.get(opts, :timeout, @connect_timeout)
    owner = self()

    # the process dials and negotiates; its start returns when both are done (or failed)
    case GenServer.start(__MODULE__, {endpoint, owner, timeout}) do
      {:ok, pid} ->
        {socket, endpoint} = GenServer.call(pid, :handle)
        {:ok, %__MODULE__{pid: pid, socket: socket, endpoint: endpoint}}

      {:error, reason} ->
        {:error, reason}
    end
  end

  @impl Vws.Links.Transport.Behaviour
  def listen(_endpoint, _opts), do: {:error, :not_listenable}

  @impl Vws.Links.Transport.Behaviour
  def listener_endpoint(_listener), do: raise(ArgumentError, "an RFC 2217 port has no listener")

  @impl Vws.Links.Transport.Behaviour
  def accept(_listener, _timeout), do: {:error, :not_listenable}

  @impl Vws.Links.Transport.Behaviour
  def close_listener(_listener), do: :ok

  @impl Vws.Links.Transport.Behaviour
  def send(%__MODULE__{socket: socket}, data), do: :gen_tcp.send(socket, Telnet.escape(data))

  @impl Vws.Links.Transport.Behaviour
  def close(%__MODULE__{pid: pid}) do
    GenServer.stop(pid, :normal)
  catch
    :exit, _ -> :ok
  end

  @impl Vws.Links.Transport.Behaviour
  def controlling_process(%__MODULE__{pid: pid}, new_owner) do
    GenServer.call(pid, {:owner, self(), new_owner})
  catch
    :exit, _ -> {:error, :closed}
  end

  @impl Vws.Links.Transport.Behaviour
  def activate(%__MODULE__{pid: pid}), do: GenServer.cast(pid, :activate)

  # (activate/1 arms one delivery already)
  @impl true
  def activate_once(conn), do: activate(conn)

  @impl Vws.Links.Transport.Behaviour
  def handle_message(%__MODULE__{pid: pid}, {:rfc2217, pid, event}) do
    case event do
      {:data, bytes} -> {:data, bytes}
      :closed -> :closed
      {:error, reason} -> {:error, reason}
    end
  end

  def handle_message(_conn, _msg), do: :unknown

  @impl Vws.Links.Transport.Behaviour
  def peer(%__MODULE__{endpoint: endpoint}), do: Endpoint.to_string(endpoint)

  @doc """
  The port's state as the server last told it: `settings` (the answers to our settings),
  `modemstate` and `linestate` bytes (nil until told), `line_errors` counted.
  """
  @spec line_state(Vws.Links.Transport.Conn.t() | t) :: map
  def line_state(%Vws.Links.Transport.Conn{handle: handle}), do: line_state(handle)
  def line_state(%__MODULE__{pid: pid}), do: GenServer.call(pid, :line_state)

  ## The connection's process

  @impl GenServer
  def init({endpoint, owner, timeout}) do
    deadline = System.monotonic_time(:millisecond) + timeout
    opts = [:binary, packet: :raw, active: false, nodelay: true]

    with {:ok, socket} <- :gen_tcp.connect(endpoint.host, endpoint.port, opts, timeout),
         s = state(socket, endpoint, owner),
         {:ok, s} <- negotiate(s, deadline) do
      Process.monitor(owner)
      {:ok, s}
    else
      {:error, reason} -> {:stop, reason}
    end
  end

  defp state(socket, endpoint, owner) do
    %{
      socket: socket,
      endpoint: endpoint,
      owner: owner,
      decoder: Telnet.decoder(),
      pending: <<>>,
      armed: false,
      com_port: :asked,
      settings: %{},
      linestate: nil,
      modemstate: nil,
      line_errors: 0,
      ended: nil
    }
  end

  # The settings the endpoint asks for, in the order sent; each answer must repeat its value.
  defp wanted(%Endpoint{serial: serial}) do
    settings = Keyword.merge(Endpoint.serial_defaults(), serial)

    [
      baud: settings[:baud],
      data_size: settings[:data_bits],
      parity: settings[:parity],
      stop_size: settings[:stop_bits],
      control: settings[:flow]
    ]
  end

  defp negotiate(s, deadline) do
    hello = [
      Telnet.option(:will, @com_port),
      Telnet.option(:do, @binary),
      Telnet.option(:will, @binary),
      Telnet.option(:do, @sga),
      Telnet.option(:will, @sga)
    ]

    with :ok <- :gen_tcp.send(s.socket, hello),
         {:ok, s} <- await(s, deadline, &(&1.com_port != :asked)),
         :ok <- if(s.com_port == :refused, do: {:error, :com_port_refused}, else: :ok),
         wanted = wanted(s.endpoint),
         :ok <-
           :gen_tcp.send(s.socket, [
             Enum.map(wanted, &Telnet.com_port/1),
             Telnet.com_port({:linestate_mask, 0x1E}),
             Telnet.com_port({:modemstate_mask, 0xFF})
           ]),
         {:ok, s} <- await(s, deadline, &(map_size(&1.settings) >= length(wanted))) do
      case Enum.find(wanted, fn {key, value} -> s.settings[key] != value end) do
        nil -> {:ok, s}
        {key, value} -> {:error, {:setting_refused, key, value, s.settings[key]}}
      end
    end
  end

  # reads (passively) until `done?` holds for the state, or the deadline
  defp await(s, deadline, done?) do
    left = deadline - System.monotonic_time(:millisecond)

    cond do
      done?.(s) ->
        {:ok, s}

      left <= 0 ->
        {:error, :negotiation_timeout}

      true ->
        case :gen_tcp.recv(s.socket, 0, left) do
          {:ok, bytes} -> s |> take(bytes) |> await(deadline, done?)
          {:error, :timeout} -> {:error, :negotiation_timeout}
          {:error, reason} -> {:error, reason}
        end
    end
  end

  @impl GenServer
  def handle_call(:handle, _from, s), do: {:reply, {s.socket, s.endpoint}, s}

  def handle_call({:owner, caller, new_owner}, _from, s) do
    if caller == s.owner do
      Process.monitor(new_owner)
      {:reply, :ok, %{s | owner: new_owner}}
    else
      {:reply, {:error, :not_owner}, s}
    end
  end

  def handle_call(:line_state, _from, s),
    do: {:reply, Map.take(s, [:settings, :linestate, :modemstate, :line_errors]), s}

  @impl GenServer
  def handle_cast(:activate, s), do: {:noreply, deliver(%{s | armed: true})}

  @impl GenServer
  def handle_info({:tcp, socket, bytes}, %{socket: socket} = s),
    do: {:noreply, s |> take(bytes) |> deliver()}

  def handle_info({:tcp_closed, socket}, %{socket: socket} = s),
    do: {:noreply, deliver(%{s | ended: :closed})}

  def handle_info({:tcp_error, socket, reason}, %{socket: socket} = s),
    do: {:noreply, deliver(%{s | ended: {:error, reason}})}

  def handle_info({:DOWN, _, :process, pid, _}, %{owner: pid} = s), do: {:stop, :normal, s}
  def handle_info({:DOWN, _, :process, _old_owner, _}, s), do: {:noreply, s}
  def handle_info(_msg, s), do: {:noreply, s}

  @impl GenServer
  def terminate(_reason, s), do: :gen_tcp.close(s.socket)

  # One chunk (or the end) to an armed owner; the socket is read only while someone waits.
  defp deliver(%{armed: false} = s), do: s

  defp deliver(%{pending: <<>>, ended: nil} = s) do
    _ = :inet.setopts(s.socket, active: :once)
    s
  end

  defp deliver(%{pending: <<>>, ended: ended} = s) do
    Kernel.send(s.owner, {:rfc2217, self(), ended})
    %{s | armed: false}
  end

  defp deliver(s) do
    Kernel.send(s.owner, {:rfc2217, self(), {:data, s.pending}})
    %{s | pending: <<>>, armed: false}
  end

  ## What the server sends

  defp take(s, bytes) do
    {events, decoder} = Telnet.decode(s.decoder, bytes)
    Enum.reduce(events, %{s | decoder: decoder}, &event/2)
  end

  defp event({:data, bytes}, s), do: %{s | pending: s.pending <> bytes}
  defp event({:do, @com_port}, s), do: %{s | com_port: :accepted}
  defp event({:dont, @com_port}, s), do: %{s | com_port: :refused}
  defp event({:wont, @com_port}, s), do: s
  defp event({:will, @com_port}, s), do: s
  # the options we asked for ourselves: accepted as they come
  defp event({verb, opt}, s) when opt in [@binary, @sga] and verb in [:do, :will, :dont, :wont],
    do: s

  defp event({:do, opt}, s), do: reply(s, Telnet.option(:wont, opt))
  defp event({:will, opt}, s), do: reply(s, Telnet.option(:dont, opt))
  defp event({verb, _opt}, s) when verb in [:dont, :wont], do: s

  defp event({:com_port, {:linestate, byte}}, s) do
    errors =
      for {bit, what} <- [{2, :overrun}, {4, :parity}, {8, :framing}, {16, :break}],
          Bitwise.band(byte, bit) != 0,
          do: what

    if errors != [] do
      Logger.warning(
        "#{Endpoint.to_string(s.endpoint)}: the serial line reports #{Enum.join(errors, ", ")} error"
      )

      Vws.Telemetry.execute([:vws, :rfc2217, :line_state], %{count: 1}, %{
        endpoint: Endpoint.to_string(s.endpoint),
        errors: errors
      })
    end

    %{s | linestate: byte, line_errors: s.line_errors + length(errors)}
  end

  defp event({:com_port, {:modemstate, byte}}, s) do
    if s.modemstate != nil and s.modemstate != byte do
      Logger.info(
        "#{Endpoint.to_string(s.endpoint)}: modem lines now carrier #{bit(byte, 0x80)}, " <>
          "DSR #{bit(byte, 0x20)}, CTS #{bit(byte, 0x10)}"
      )
    end

    %{s | modemstate: byte}
  end

  defp event({:com_port, {key, value}}, s)
       when key in [:baud, :data_size, :parity, :stop_size, :control],
       do: %{s | settings: Map.put(s.settings, key, value)}

  defp event(other, s) do
    Logger.debug("RFC 2217: #{inspect(other)} ignored")
    s
  end

  defp bit(byte, mask), do: if(Bitwise.band(byte, mask) != 0, do: "on", else: "off")

  defp reply(s, bytes) do
    _ = :gen_tcp.send(s.socket, bytes)
    s
  end
end
