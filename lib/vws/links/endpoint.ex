defmodule Vws.Links.Endpoint do
  @moduledoc """
  Where a link is plugged in: a TCP address, a serial line, or an in-memory loopback name.

  Every link of the workstation is configured by one string, so real equipment, a terminal
  server (ser2net, Moxa), our simulators or an outside test tool can be put at the other end:

    * `tcp://host:port` — a host name or dotted IPv4 address and a port in `0..65535`
      (port `0` asks the system for an ephemeral port when listening);
    * `tty:/dev/ttyS0?baud=9600&data_bits=8&parity=none&stop_bits=1&flow=none` — a serial device.
      The query is optional; each setting defaults to 9600 baud, 8 data bits, no parity, 1 stop
      bit, no flow control (`flow` is `none`, `xonxoff` or `rtscts`). A bare absolute path
      (`/dev/ttyUSB0`) means the same as `tty:/dev/ttyUSB0`;
    * `rfc2217://host:port?baud=4800&parity=even…` — a serial port behind a terminal server that
      speaks RFC 2217 (Telnet COM Port Control, e.g. ser2net's `telnet(rfc2217)` accepter): the
      same settings as a tty, which the CEC sets on the server's port
      (`Vws.Links.Transport.RFC2217`). A plain `tcp://` endpoint carries bytes only: a serial
      setting on it is refused, as it could never be applied;
    * `loopback:name` — an in-memory pair inside this node (see `Vws.Links.Transport.Loopback`);
    * `cell:id` — the WC link of workstation `id`, wherever it runs in the cell of connected
      nodes (see `Vws.CEC.Cell.connect/2`, which resolves it above the transports); it can be connected to, not listened on.

  `to_string/1` gives the canonical form, which parses back to the same endpoint:

      iex> {:ok, e} = Vws.Links.Endpoint.parse("tty:/dev/ttyS1?parity=even&data_bits=7")
      iex> e.serial
      [baud: 9600, data_bits: 7, parity: :even, stop_bits: 1, flow: :none]
      iex> to_string(e)
      "tty:/dev/ttyS1?baud=9600&data_bits=7&parity=even&stop_bits=1"
      iex> to_string(Vws.Links.Endpoint.parse!("rfc2217://ts-1:2001?baud=4800&flow=xonxoff"))
      "rfc2217://ts-1:2001?baud=4800&data_bits=8&parity=none&stop_bits=1&flow=xonxoff"
      iex> Vws.Links.Endpoint.parse!("tcp://127.0.0.1:5001")
      %Vws.Links.Endpoint{kind: :tcp, host: ~c"127.0.0.1", port: 5001, path: nil, name: nil, serial: []}
      iex> {:error, error} = Vws.Links.Endpoint.parse("tcp://vmc:70000")
      iex> Exception.message(error)
      ~s(invalid endpoint "tcp://vmc:70000": the port must be a number from 0 to 65535)

  Endpoints built in code may use any term as a loopback `name` or a cell workstation id; only
  string names have a string form that parses back to the same endpoint.
  """

  import Kernel, except: [to_string: 1]

  alias Vws.Links.Endpoint.Error

  @enforce_keys [:kind]
  defstruct kind: nil, host: nil, port: nil, path: nil, name: nil, serial: []

  @type kind :: :tcp | :tty | :rfc2217 | :loopback | :cell
  @type parity :: :none | :even | :odd
  @type flow :: :none | :xonxoff | :rtscts
  @type serial :: [
          baud: pos_integer(),
          data_bits: 5..8,
          parity: parity(),
          stop_bits: 1..2,
          flow: flow()
        ]
  @type t :: %__MODULE__{
          kind: kind(),
          host: charlist() | nil,
          port: 0..65535 | nil,
          path: String.t() | nil,
          name: term() | nil,
          serial: serial() | []
        }

  @serial_defaults [baud: 9600, data_bits: 8, parity: :none, stop_bits: 1, flow: :none]
  @serial_keys Keyword.keys(@serial_defaults)

  # The speeds termios (and so socat's b<rate> options and Circuits.UART) know on Linux.
  @bauds [50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400] ++
           [57600, 115_200, 230_400, 460_800, 500_000, 576_000, 921_600, 1_000_000] ++
           [1_152_000, 1_500_000, 2_000_000, 2_500_000, 3_000_000, 3_500_000, 4_000_000]

  @max_host 253
  @max_label 63
  @max_name 255
  @max_path 4096

  @doc "The baud rates a `tty:` endpoint accepts."
  @spec bauds() :: [pos_integer()]
  def bauds, do: @bauds

  @doc "The serial settings used for every key a `tty:` endpoint leaves out."
  @spec serial_defaults() :: serial()
  def serial_defaults, do: @serial_defaults

  @doc """
  Parses an endpoint string.

  Returns `{:error, %Vws.Links.Endpoint.Error{}}` naming what is wrong; never raises, whatever the input.
  """
  @spec parse(String.t()) :: {:ok, t()} | {:error, Error.t()}
  def parse(input) when is_binary(input) do
    case do_parse(input) do
      {:ok, endpoint} -> {:ok, endpoint}
      {:error, reason, detail} -> {:error, %Error{reason: reason, input: input, detail: detail}}
    end
  end

  def parse(input), do: {:error, %Error{reason: :not_a_string, input: input}}

  @doc "Like `parse/1` but raises `Vws.Links.Endpoint.Error`."
  @spec parse!(String.t()) :: t()
  def parse!(input) do
    case parse(input) do
      {:ok, endpoint} -> endpoint
      {:error, error} -> raise error
    end
  end

  @doc """
  The canonical string form of an endpoint; `tty:` and `rfc2217:` endpoints always list baud,
  data bits, parity and stop bits, and flow control when there is any.

      iex> Vws.Links.Endpoint.to_string(Vws.Links.Endpoint.parse!("/dev/ttyUSB0"))
      "tty:/dev/ttyUSB0?baud=9600&data_bits=8&parity=none&stop_bits=1"
  """
  @spec to_string(t()) :: String.t()
  def to_string(%__MODULE__{kind: :tcp, host: host, port: port}),
    do: "tcp://#{host}:#{port}"

  def to_string(%__MODULE__{kind: :tty, path: path, serial: serial}),
    do: "tty:#{path}?#{query(serial)}"

  def to_string(%__MODULE__{kind: :rfc2217, host: host, port: port, serial: serial}),
    do: "rfc2217://#{host}:#{port}?#{query(serial)}"

  def to_string(%__MODULE__{kind: :loopback, name: name}) when is_binary(name),
    do: "loopback:#{name}"

  def to_string(%__MODULE__{kind: :loopback, name: name}), do: "loopback:#{inspect(name)}"

  def to_string(%__MODULE__{kind: :cell, name: id}) when is_binary(id), do: "cell:#{id}"
  def to_string(%__MODULE__{kind: :cell, name: id}), do: "cell:#{inspect(id)}"

  # flow=none is left out: endpoints written before flow control existed keep their form
  defp query(serial) do
    settings = Keyword.merge(@serial_defaults, serial)

    @serial_keys
    |> Enum.reject(&(&1 == :flow and settings[:flow] == :none))
    |> Enum.map_join("&", fn key -> "#{key}=#{Keyword.fetch!(settings, key)}" end)
  end

  ## Parsing

  defp do_parse("tcp://" <> rest), do: parse_tcp(rest)
  defp do_parse("tty:" <> rest), do: parse_tty(rest)
  defp do_parse("rfc2217://" <> rest), do: parse_rfc2217(rest)
  defp do_parse("/" <> _ = path), do: parse_tty(path)
  defp do_parse("loopback:" <> name), do: parse_loopback(name)
  defp do_parse("cell:" <> id), do: parse_cell(id)
  defp do_parse(_), do: {:error, :unknown_scheme, nil}

  defp parse_tcp(rest) do
    case :binary.split(rest, "?") do
      [_address, _query] ->
        {:error, :serial_on_tcp, nil}

      [address] ->
        parse_host_port(address)
    end
  end

  defp parse_rfc2217(rest) do
    {address, query} =
      case :binary.split(rest, "?") do
        [address] -> {address, ""}
        [address, query] -> {address, query}
      end

    with {:ok, %__MODULE__{host: host, port: port}} <- parse_host_port(address),
         :ok <- if(port == 0, do: {:error, :bad_port, nil}, else: :ok),
         {:ok, serial} <- parse_query(query) do
      {:ok, %__MODULE__{kind: :rfc2217, host: host, port: port, serial: serial}}
    end
  end

  defp parse_host_port(rest) do
    case :binary.split(rest, ":", [:global]) do
      [_host] ->
        {:error, :missing_port, nil}

      [host, port] ->
        with :ok <- check_host(host),
             {:ok, port} <- parse_port(port) do
          {:ok, %__MODULE__{kind: :tcp, host: String.to_charlist(host), port: port}}
        end

      _ ->
        {:error, :bad_host, "only host names and IPv4 addresses are supported"}
    end
  end

  defp check_host(""), do: {:error, :bad_host, "the host is empty"}

  defp check_host(host) when byte_size(host) > @max_host,
    do: {:error, :bad_host, "the host is longer than #{@max_host} characters"}

  defp check_host(host) do
    cond do
      host =~ ~r/\A[0-9.]+\z/ -> check_ipv4(host)
      Enum.all?(String.split(host, "."), &label?/1) -> :ok
      true -> {:error, :bad_host, nil}
    end
  end

  defp check_ipv4(host) do
    parts = String.split(host, ".")

    if length(parts) == 4 and Enum.all?(parts, &octet?/1),
      do: :ok,
      else: {:error, :bad_host, "#{host} is not a valid IPv4 address"}
  end

  defp octet?("0"), do: true
  defp octet?("0" <> _), do: false

  defp octet?(part),
    do: byte_size(part) in 1..3 and String.to_integer(part) <= 255

  defp label?(label) do
    byte_size(label) in 1..@max_label and
      label =~ ~r/\A[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?\z/
  end

  defp parse_port(port) do
    if port =~ ~r/\A[0-9]{1,5}\z/ and String.to_integer(port) <= 65535,
      do: {:ok, String.to_integer(port)},
      else: {:error, :bad_port, nil}
  end

  defp parse_tty(rest) do
    {path, query} =
      case :binary.split(rest, "?") do
        [path] -> {path, ""}
        [path, query] -> {path, query}
      end

    with :ok <- check_path(path),
         {:ok, serial} <- parse_query(query) do
      {:ok, %__MODULE__{kind: :tty, path: path, serial: serial}}
    end
  end

  # The path ends up inside a socat address, where `,` `:` `!` quotes and backslashes are syntax.
  defp check_path(""), do: {:error, :bad_path, "the path is empty"}

  defp check_path(path) do
    cond do
      not String.starts_with?(path, "/") ->
        {:error, :bad_path, "the path must be absolute"}

      byte_size(path) > @max_path ->
        {:error, :bad_path, "the path is too long"}

      not String.valid?(path) or path =~ ~r/[\x00-\x20\x7f,:!'"\\&=#]/u ->
        {:error, :bad_path,
         "it may not hold spaces, control characters or any of , : ! ' \" \\ & = #"}

      true ->
        :ok
    end
  end

  defp parse_query(""), do: {:ok, @serial_defaults}

  defp parse_query(query) do
    query
    |> String.split("&")
    |> Enum.reduce_while({:ok, []}, fn pair, {:ok, acc} ->
      case parse_setting(pair) do
        {:ok, {key, value}} ->
          if Keyword.has_key?(acc, key),
            do: {:halt, {:error, :duplicate_option, Atom.to_string(key)}},
            else: {:cont, {:ok, [{key, value} | acc]}}

        error ->
          {:halt, error}
      end
    end)
    |> case do
      {:ok, given} ->
        {:ok, Enum.map(@serial_keys, fn key -> {key, given[key] || @serial_defaults[key]} end)}

      error ->
        error
    end
  end

  defp parse_setting(pair) do
    case :binary.split(pair, "=") do
      ["baud", value] -> setting(:baud, value, :bad_baud, &baud/1)
      ["data_bits", value] -> setting(:data_bits, value, :bad_data_bits, &data_bits/1)
      ["parity", value] -> setting(:parity, value, :bad_parity, &parity/1)
      ["stop_bits", value] -> setting(:stop_bits, value, :bad_stop_bits, &stop_bits/1)
      ["flow", value] -> setting(:flow, value, :bad_flow, &flow/1)
      [key, _value] -> {:error, :unknown_option, printable(key)}
      [_no_equals] -> {:error, :bad_option, printable(pair)}
    end
  end

  defp setting(key, value, reason, fun) do
    case fun.(value) do
      {:ok, parsed} -> {:ok, {key, parsed}}
      :error -> {:error, reason, printable(value)}
    end
  end

  defp baud(value) do
    with true <- value =~ ~r/\A[0-9]{1,7}\z/,
         baud = String.to_integer(value),
         true <- baud in @bauds do
      {:ok, baud}
    else
      _ -> :error
    end
  end

  defp data_bits(value) when value in ["5", "6", "7", "8"], do: {:ok, String.to_integer(value)}
  defp data_bits(_), do: :error

  defp parity("none"), do: {:ok, :none}
  defp parity("even"), do: {:ok, :even}
  defp parity("odd"), do: {:ok, :odd}
  defp parity(_), do: :error

  defp stop_bits("1"), do: {:ok, 1}
  defp stop_bits("2"), do: {:ok, 2}
  defp stop_bits(_), do: :error

  defp flow("none"), do: {:ok, :none}
  defp flow("xonxoff"), do: {:ok, :xonxoff}
  defp flow("rtscts"), do: {:ok, :rtscts}
  defp flow(_), do: :error

  defp parse_loopback(""), do: {:error, :bad_name, "the name is empty"}

  defp parse_loopback(name) do
    cond do
      byte_size(name) > @max_name ->
        {:error, :bad_name, "the name is longer than #{@max_name} bytes"}

      not String.printable?(name) or name =~ ~r/\s/u ->
        {:error, :bad_name, nil}

      true ->
        {:ok, %__MODULE__{kind: :loopback, name: name}}
    end
  end

  # A workstation id follows the rules of a loopback name.
  defp parse_cell(id) do
    with {:ok, %__MODULE__{name: id}} <- parse_loopback(id) do
      {:ok, %__MODULE__{kind: :cell, name: id}}
    end
  end

  # Details echo user input into messages; keep them short and printable.
  defp printable(text) do
    text = if String.valid?(text), do: text, else: inspect(text, binaries: :as_binaries)
    String.slice(text, 0, 40)
  end

  defimpl String.Chars do
    def to_string(endpoint), do: Vws.Links.Endpoint.to_string(endpoint)
  end
end
