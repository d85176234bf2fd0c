defmodule Vws.Links.Transport.Serial do
  @moduledoc """
  `Vws.Links.Transport` over a serial line (`tty:/dev/ttyS0?baud=9600&...`), client side only.

  OTP has no tty driver, so the device is opened by a well-kept outside program, chosen by the
  `backend` option of `connect/2`:

    * `:socat` — `socat` runs as an Erlang port, its standard input and output relayed to the
      device, which it configures with termios (see `socat_args/1`). The executable is found on
      the `PATH`, or given with the `socat` option.
    * `:circuits_uart` — [Circuits.UART](https://hex.pm/packages/circuits_uart), when that library
      is part of the release. It is called through `apply/3`, so this module compiles without it.
      **Untested here**: our build machines cannot fetch hex packages; the calls follow its
      documented API (`start_link/0`, `open/3` with `active: true, id: :pid`, `write/2`,
      `controlling_process/2`, `close/1`, `stop/1`).
    * `:auto` (default) — Circuits.UART if `Code.ensure_loaded?(Circuits.UART)`, else socat.

  ## Always active

  Neither backend can hold received bytes back: an Erlang port delivers everything its program
  writes, and Circuits.UART's active mode does the same. So a serial connection is always active:
  `activate/1` is accepted and does nothing, and data arrives as it comes. Protocol code written
  for active-once (see `Vws.Links.Transport`) works unchanged; it simply never waits.

  ## Messages

  With socat the controlling process receives the port's messages: `{port, {:data, bytes}}`, and
  `{port, {:exit_status, status}}` when socat ends: `{:error, :device_gone}` when the device's
  path no longer exists (a USB adapter pulled out, a pty whose other side closed), else status
  0 is `:closed` and any other `{:error, {:socat_exit, status}}`. A link with an endpoint
  reopens the device when it is back (`Vws.Links.Connection`'s back-off). A
  process trapping exits also gets `{:EXIT, port, reason}`; `handle_message/2` classifies it too.
  With Circuits.UART: `{:circuits_uart, pid, bytes | {:error, reason}}`.

  ## Closing

  `close/1` closes the port; socat writes out what it has already been given, sees the end of its
  input and exits. `close/1` returns once the socat process is gone, killing it if it has not
  exited within `close_timeout` (option of `connect/2`, default 2000 ms; output still queued for
  a slow line is then lost). If the controlling process dies, the port closes with it and socat
  exits the same way.
  """

  @behaviour Vws.Links.Transport.Behaviour

  import Kernel, except: [send: 2]

  alias Vws.Links.Endpoint

  @enforce_keys [:backend, :endpoint]
  defstruct [:backend, :endpoint, :port, :os_pid, :uart, close_timeout: 2000]

  @type t :: %__MODULE__{
          backend: :socat | :circuits_uart,
          endpoint: Endpoint.t(),
          port: port() | nil,
          os_pid: non_neg_integer() | nil,
          uart: pid() | nil,
          close_timeout: non_neg_integer()
        }

  @circuits_uart Circuits.UART
  # After its input ends socat waits this long for the device side before exiting (socat -t).
  @socat_linger "0.05"

  @impl true
  def connect(%Endpoint{kind: :tty} = endpoint, opts) do
    case backend(Keyword.get(opts, :backend, :auto)) do
      :socat -> open_socat(endpoint, opts)
      :circuits_uart -> open_circuits_uart(endpoint, opts)
      other -> {:error, {:unknown_backend, other}}
    end
  end

  defp backend(:auto),
    do: if(Code.ensure_loaded?(@circuits_uart), do: :circuits_uart, else: :socat)

  defp backend(backend), do: backend

  @impl true
  def listen(_endpoint, _opts), do: {:error, :not_listenable}

  @impl true
  def listener_endpoint(_listener), do: raise(ArgumentError, "a serial line has no listener")

  @impl true
  def accept(_listener, _timeout), do: {:error, :not_listenable}

  @impl true
  def close_listener(_listener), do: :ok

  @doc """
  The arguments socat is started with for a `tty:` endpoint.

  The line is put in raw mode flag by flag rather than with socat's `raw`/`rawer`/`cfmakeraw`:
  those also reset the character size and parity, and socat does not promise to apply options
  in the order given. With parity on, bytes with a parity error are dropped (`inpck`, `ignpar`):
  a garbled byte is a lost byte, which the link protocols detect and recover from. Modem control
  lines are ignored (`clocal`), and the device does not become socat's controlling terminal
  (`noctty`), so a hang-up ends socat instead of sending it a SIGHUP. Flow control is the
  endpoint's `flow`: `xonxoff` lets the tty driver stop sending on the peer's XOFF and send XOFF
  itself when its input fills (`ixon`, `ixoff`; the driver then keeps DC1/DC3 from the link),
  `rtscts` uses the RTS/CTS lines (`crtscts`), `none` neither.

      iex> Vws.Links.Transport.Serial.socat_args(Vws.Links.Endpoint.parse!("tty:/dev/ttyS0?baud=4800&data_bits=7&parity=even"))
      ["-t", "0.05", "STDIO",
       "FILE:/dev/ttyS0,noctty,b4800,cs7,parenb=1,parodd=0,cstopb=0,inpck=1,ignpar=1," <>
         "echo=0,icanon=0,isig=0,iexten=0,opost=0,icrnl=0,inlcr=0,igncr=0,istrip=0," <>
         "brkint=0,ignbrk=0,parmrk=0,clocal=1,min=1,time=0,ixon=0,ixoff=0,crtscts=0"]

      iex> Vws.Links.Transport.Serial.socat_args(Vws.Links.Endpoint.parse!("tty:/dev/ttyS0?flow=xonxoff")) |> List.last() |> String.split(",") |> Enum.take(-3)
      ["ixon=1", "ixoff=1", "crtscts=0"]
  """
  @spec socat_args(Endpoint.t()) :: [String.t()]
  def socat_args(%Endpoint{kind: :tty, path: path, serial: serial}) do
    settings = Keyword.merge(Endpoint.serial_defaults(), serial)
    parity = settings[:parity]
    checked = if parity == :none, do: 0, else: 1

    termios = [
      "b#{settings[:baud]}",
      "cs#{settings[:data_bits]}",
      "parenb=#{checked}",
      "parodd=#{if parity == :odd, do: 1, else: 0}",
      "cstopb=#{if settings[:stop_bits] == 2, do: 1, else: 0}",
      "inpck=#{checked}",
      "ignpar=#{checked}",
      "echo=0,icanon=0,isig=0,iexten=0,opost=0,icrnl=0,inlcr=0,igncr=0,istrip=0",
      "brkint=0,ignbrk=0,parmrk=0,clocal=1,min=1,time=0",
      flow(settings[:flow])
    ]

    ["-t", @socat_linger, "STDIO", Enum.join(["FILE:#{path}", "noctty" | termios], ",")]
  end

  defp flow(:none), do: "ixon=0,ixoff=0,crtscts=0"
  defp flow(:xonxoff), do: "ixon=1,ixoff=1,crtscts=0"
  defp flow(:rtscts), do: "ixon=0,ixoff=0,crtscts=1"

  defp open_socat(%Endpoint{path: path} = endpoint, opts) do
    with {:ok, socat} <- find_socat(opts),
         :ok <- check_device(path) do
      port =
        Port.open({:spawn_executable, socat}, [
          :binary,
          :exit_status,
          :stream,
          :use_stdio,
          args: socat_args(endpoint)
        ])

      {:os_pid, os_pid} = Port.info(port, :os_pid)

      {:ok,
       %__MODULE__{
         backend: :socat,
         endpoint: endpoint,
         port: port,
         os_pid: os_pid,
         close_timeout: Keyword.get(opts, :close_timeout, 2000)
       }}
    end
  end

  defp find_socat(opts) do
    case System.find_executable(Keyword.get(opts, :socat, "socat")) do
      nil -> {:error, :socat_not_found}
      path -> {:ok, path}
    end
  end

  # socat reports a device it cannot open only by exiting; catch the common cases here so that
  # connect/2 can say what is wrong.
  defp check_device(path) do
    case File.stat(path) do
      {:ok, %File.Stat{type: :device, access: :read_write}} -> :ok
      {:ok, %File.Stat{type: :device}} -> {:error, :eacces}
      {:ok, %File.Stat{}} -> {:error, :not_a_tty}
      {:error, reason} -> {:error, reason}
    end
  end

  defp open_circuits_uart(%Endpoint{path: path, serial: serial} = endpoint, _opts) do
    settings = Keyword.merge(Endpoint.serial_defaults(), serial)

    uart_opts = [
      speed: settings[:baud],
      data_bits: settings[:data_bits],
      parity: settings[:parity],
      stop_bits: settings[:stop_bits],
      flow_control:
        case settings[:flow] do
          :none -> :none
          :xonxoff -> :software
          :rtscts -> :hardware
        end,
      active: true,
      id: :pid
    ]

    {:ok, uart} = apply(@circuits_uart, :start_link, [])

    case apply(@circuits_uart, :open, [uart, path, uart_opts]) do
      :ok ->
        {:ok, %__MODULE__{backend: :circuits_uart, endpoint: endpoint, uart: uart}}

      {:error, reason} ->
        apply(@circuits_uart, :stop, [uart])
        {:error, reason}
    end
  end

  @impl true
  def send(%__MODULE__{backend: :socat, port: port}, data) do
    Port.command(port, data)
    :ok
  rescue
    ArgumentError -> {:error, :closed}
  end

  def send(%__MODULE__{backend: :circuits_uart, uart: uart}, data) do
    apply(@circuits_uart, :write, [uart, data])
  catch
    :exit, _ -> {:error, :closed}
  end

  @impl true
  def close(%__MODULE__{backend: :socat, port: port, os_pid: os_pid, close_timeout: timeout}) do
    try do
      Port.close(port)
    rescue
      ArgumentError -> :ok
    end

    await_exit(os_pid, System.monotonic_time(:millisecond) + timeout)
  end

  def close(%__MODULE__{backend: :circuits_uart, uart: uart}) do
    apply(@circuits_uart, :close, [uart])
    apply(@circuits_uart, :stop, [uart])
    :ok
  catch
    :exit, _ -> :ok
  end

  @impl true
  def controlling_process(%__MODULE__{backend: :socat, port: port}, pid) do
    case Port.info(port, :connected) do
      {:connected, owner} when owner == self() ->
        Port.connect(port, pid)
        # Port.connect/2 leaves the old owner linked; the new owner is the one to live with it.
        Process.unlink(port)
        :ok

      {:connected, _} ->
        {:error, :not_owner}

      nil ->
        {:error, :closed}
    end
  end

  def controlling_process(%__MODULE__{backend: :circuits_uart, uart: uart}, pid) do
    apply(@circuits_uart, :controlling_process, [uart, pid])
  catch
    :exit, _ -> {:error, :closed}
  end

  @impl true
  def activate(%__MODULE__{}), do: :ok

  # (always active: a tty cannot hold bytes back, and a line's pump counts what overruns it)
  @impl true
  def activate_once(%__MODULE__{}), do: :ok

  @impl true
  def handle_message(%__MODULE__{backend: :socat, port: port, endpoint: endpoint}, msg) do
    case msg do
      {^port, {:data, data}} -> {:data, data}
      {^port, {:exit_status, status}} -> ended(endpoint, status)
      {:EXIT, ^port, :normal} -> :closed
      {:EXIT, ^port, reason} -> {:error, reason}
      _ -> :unknown
    end
  end

  def handle_message(%__MODULE__{backend: :circuits_uart, uart: uart}, msg) do
    case msg do
      {:circuits_uart, ^uart, {:error, reason}} -> {:error, reason}
      {:circuits_uart, ^uart, data} when is_binary(data) -> {:data, data}
      _ -> :unknown
    end
  end

  # socat ended: a device whose path is gone was unplugged (a USB adapter pulled, the other end
  # of a pty closed) — said as such, so the log tells it from a line that merely hung up
  defp ended(%Endpoint{path: path}, status) do
    cond do
      not File.exists?(path) -> {:error, :device_gone}
      status == 0 -> :closed
      true -> {:error, {:socat_exit, status}}
    end
  end

  @impl true
  def peer(%__MODULE__{endpoint: endpoint}), do: Endpoint.to_string(endpoint)

  ## Making sure socat is gone

  defp await_exit(os_pid, deadline) do
    cond do
      not os_alive?(os_pid) ->
        :ok

      System.monotonic_time(:millisecond) >= deadline ->
        System.cmd("kill", ["-KILL", Integer.to_string(os_pid)], stderr_to_stdout: true)
        :ok

      true ->
        Process.sleep(5)
        await_exit(os_pid, deadline)
    end
  end

  @doc false
  # Whether an OS process is still running (a zombie waiting to be reaped counts as gone).
  @spec os_alive?(non_neg_integer()) :: boolean()
  def os_alive?(os_pid) do
    if File.dir?("/proc/self") do
      case File.read("/proc/#{os_pid}/stat") do
        {:ok, stat} -> not zombie?(stat)
        {:error, _} -> false
      end
    else
      {_, status} = System.cmd("kill", ["-0", Integer.to_string(os_pid)], stderr_to_stdout: true)
      status == 0
    end
  end

  # The state letter follows the parenthesised command name, which may itself hold ") ".
  defp zombie?(stat) do
    case :binary.matches(stat, ") ") do
      [] -> false
      matches -> binary_part(stat, elem(List.last(matches), 0) + 2, 1) in ["Z", "X"]
    end
  end
end
