defmodule Vws.Links.HPIB do
  @moduledoc """
  The HPIB (IEEE-488) bus of the CEC (seed §1.3, PROTOCOLS.md §4): devices by primary address,
  each reached through its own `Vws.Links.Transport` endpoint — a LAN instrument's raw SCPI socket
  (`tcp://daq1:5025`), a GPIB gateway, a simulator, or a loopback pair in tests.

  One process per device (`start_link/1`, usually under the workstation's links supervisor)
  owns the connection, sends requests one at a time in the order they come, matches each answer
  line to its query, and reconnects with a growing back-off when the endpoint is lost. Callers
  speak SCPI terms (`Vws.Codecs.SCPI`), so the same bus serves DAQ #1 and the hydraulic controller:

      iex> {:ok, plant} = Vws.Sim.Plant.start_link(time_scale: 0)
      iex> {:ok, daq} = Vws.Sim.DAQ.start_link(plant: plant, endpoint: "loopback:hpib-doc")
      iex> {:ok, _} = Vws.Links.HPIB.start_link(bus: "doc", address: 9, endpoint: "loopback:hpib-doc")
      iex> Vws.Links.HPIB.await_connected({"doc", 9}, 1000)
      :ok
      iex> Vws.Links.HPIB.write({"doc", 9}, {:rout_clos, [207]})
      :ok
      iex> Vws.Links.HPIB.query({"doc", 9}, {:rout_clos?, [207]})
      {:ok, [true]}
      iex> {:ok, [[_volts], [ohms]]} =
      ...>   Vws.Links.HPIB.transaction({"doc", 9}, [{:meas_volt_dc?, [103]}, {:meas_res?, [117]}])
      iex> round(ohms)
      350
      iex> GenServer.stop(daq)
      :ok

  ## Requests

  A request is a list of commands sent back to back in one write; it succeeds with one result per
  command — the decoded response of a query, `:ok` for a command without a response — or fails
  as a whole with a `Vws.Links.HPIB.Error`. Its timeout (ms, default the device's `:timeout`) counts
  from the moment it is made, waiting behind other requests included. A request whose time runs
  out while the device is answering closes the connection (a late answer must never be taken for
  the answer to a later query); the device process reconnects at once. While the endpoint is not
  connected, requests fail at once with `:not_connected` rather than wait (only while a
  connection attempt is under way do they wait for its outcome): callers (VWS_STATUS's poll, a
  partition's command) decide what a missing answer means.

  A request whose answer comes back damaged (a line that does not decode as the answer to its
  query) or does not come within its share of the time is tried again — at most `:retries` times (default 2), within the request's own timeout, each try
  waiting an equal share of the time left — if every command of it can be repeated with the
  same effect (`Vws.Codecs.SCPI.repeatable?/1`: the reading queries and the relay settings; never
  `CLAMP_PALLET`, `*RST` or `SYST:ERR?`). Before each new try the connection is closed and
  opened again, as a device clear: no late or shifted line of the lost try can then be taken for
  the answer to another query. (Decision: SCPI lines carry no check of their own; on a line that
  can damage bytes this is what the bus driver can do.) Each try again is counted in telemetry.
  A connection the device closes ends the request `:closed` without a try again: the back-off
  (`Vws.Links.Backoff`) decides when to dial a peer that drops connections.

  `send_request/3` and `check_response/2` make the same request without blocking the caller
  (`Vws.Links.Connection.send_request/3` underneath: the device answers by the request's
  deadline at the latest), for a process that must keep its own schedule.

  ## Telemetry

  | event | measurements | metadata |
  |-------|--------------|----------|
  | `[:vws, :hpib, :connected]`    | `count` | `bus, address, endpoint` |
  | `[:vws, :hpib, :disconnected]` | `count` | `bus, address, endpoint, reason` |
  | `[:vws, :hpib, :connect_failed]` | `count`, `retry_in` (ms to the next attempt) | `bus, address, endpoint, reason` |
  | `[:vws, :hpib, :timeout]`      | `count` | `bus, address, endpoint, commands` |
  | `[:vws, :hpib, :retry]`        | `count` | `bus, address, endpoint, commands, reason, try` |
  """

  alias Vws.Links.Connection
  alias Vws.Links.HPIB.{Device, Error}

  @type bus :: term
  @type address :: 0..30
  @type device :: {bus, address}
  @type result :: Vws.Codecs.SCPI.response() | :ok
  @type request_id :: {address, Connection.request_id()}

  # how long a caller waits for a request without a timeout of its own (the device ends it
  # after its own default `:timeout`, much sooner)
  @default_wait 60_000

  # (a function: a captured function in an attribute would be a compile-time dependency)
  defp schema do
    [
      bus: [type: :any, required: true],
      address: [type: {:in, 0..30}, required: true],
      endpoint: [type: {:custom, &Connection.check_endpoint/1}, required: true],
      timeout: [type: :pos_integer],
      connect_timeout: [type: :pos_integer],
      backoff: [type: {:custom, &Connection.check_backoff/1}],
      retries: [type: :non_neg_integer],
      device: [type: {:or, [nil, :string]}]
    ]
  end

  @doc false
  def child_spec(opts) do
    %{
      id: {__MODULE__, Keyword.fetch!(opts, :bus), Keyword.fetch!(opts, :address)},
      start: {__MODULE__, :start_link, [opts]}
    }
  end

  @doc """
  Starts the process of one device. Options:

    * `:bus` — the bus's name (any term; a workstation uses its id) — required;
    * `:address` — the primary address, 0–30 — required;
    * `:endpoint` — where the device is reached (`Vws.Links.Endpoint` string or struct) — required;
    * `:timeout` — default request timeout in ms (1000);
    * `:connect_timeout` — ms allowed to open the endpoint (1000);
    * `:backoff` — `{first_ms, max_ms}` between reconnection attempts, doubling (`{50, 2000}`),
      back to `first_ms` only once the device has answered on a connection (`Vws.Links.Backoff`);
    * `:retries` — how many times a repeatable request is tried again (2);
    * `:device` — what the device is, for people (`"DAQ #1"`), shown by `info/1` and the dashboard.

  Checked first (`Vws.Options`): an unknown option or a bad value raises `Vws.Options.Error`
  naming it.
  """
  @spec start_link(keyword) :: :gen_statem.start_ret()
  def start_link(opts) do
    opts = Vws.Options.validate!(opts, schema(), "HPIB")
    :gen_statem.start_link(name(opts[:bus], opts[:address]), Device, opts, [])
  end

  @doc "The registered name of a device process."
  @spec name(bus, address) :: GenServer.name()
  def name(bus, address), do: Vws.Names.via(bus, {:hpib, address})

  @doc "The pid of a device process, or nil."
  @spec whereis(device) :: pid | nil
  def whereis({bus, address}), do: Vws.Names.whereis(bus, {:hpib, address})

  @doc "Sends one query and returns its decoded response."
  @spec query(device, Vws.Codecs.SCPI.command(), timeout | nil) ::
          {:ok, result} | {:error, Error.t()}
  def query(device, command, timeout \\ nil) do
    with {:ok, [result]} <- transaction(device, [command], timeout), do: {:ok, result}
  end

  @doc "Sends one command that has no response."
  @spec write(device, Vws.Codecs.SCPI.command(), timeout | nil) :: :ok | {:error, Error.t()}
  def write(device, command, timeout \\ nil) do
    with {:ok, [_]} <- transaction(device, [command], timeout), do: :ok
  end

  @doc "Sends several commands back to back; one result per command, or the first failure."
  @spec transaction(device, [Vws.Codecs.SCPI.command()], timeout | nil) ::
          {:ok, [result]} | {:error, Error.t()}
  def transaction({bus, address} = device, commands, timeout \\ nil) do
    {request, wait} = request(device, commands, timeout)

    # the device honours the deadline (the request is never sent after it, and a late answer
    # closes the connection); an answer after it never reaches this caller
    case Connection.call(name(bus, address), request, wait) do
      {:ok, reply} -> reply
      {:error, :timeout} -> {:error, %Error{reason: :timeout, address: address, detail: wait}}
      {:error, {:exit, _}} -> {:error, %Error{reason: :no_device, address: address}}
    end
  end

  @doc """
  Makes a transaction without waiting for it; the answer arrives as a message to pass to
  `check_response/2`.
  """
  @spec send_request(device, [Vws.Codecs.SCPI.command()], timeout | nil) :: request_id
  def send_request({bus, address} = device, commands, timeout \\ nil) do
    {request, wait} = request(device, commands, timeout)
    {address, Connection.send_request(name(bus, address), request, wait)}
  end

  @doc """
  Tells whether `msg` is the answer to `request_id`: `{:ok, results}` or `{:error, error}` if it
  is, `:no_reply` if the message is something else.
  """
  @spec check_response(term, request_id) :: {:ok, [result]} | {:error, Error.t()} | :no_reply
  def check_response(msg, {address, request_id}) do
    case Connection.check_response(msg, request_id) do
      {:ok, reply} -> reply
      :no_reply -> :no_reply
      {:error, {:exit, _reason}} -> {:error, %Error{reason: :no_device, address: address}}
    end
  end

  @doc """
  The device process's state: `%{state, device, address, endpoint, connects, timeouts, retried,
  requests, queued, unsolicited, last_error}` (`retried`: requests tried again; `device`: the
  `:device` option or nil) (`state` is `:connecting`, `:disconnected`, `:ready` or `:busy`).

  Asked by `{bus, address}` or by the device process's pid — the way every link under a
  workstation's links supervisor is asked (`Vws.Ops.Inspect.link_rows/1`).
  """
  @spec info(device | pid) :: map
  def info(pid) when is_pid(pid), do: :gen_statem.call(pid, :info)
  def info({bus, address}), do: :gen_statem.call(name(bus, address), :info)

  @doc """
  Waits until the device is connected (for start-up and tests): `:ok` or `:timeout`. The device
  process answers when it reaches `:ready` (the request waits, postponed, in its other states);
  a device that is not started answers `:timeout`.
  """
  @spec await_connected(device, non_neg_integer) :: :ok | :timeout
  def await_connected(device, timeout) do
    server = if is_pid(device), do: device, else: name(elem(device, 0), elem(device, 1))

    case Connection.call(server, :await_connected, timeout) do
      {:ok, :ok} -> :ok
      {:error, _} -> :timeout
    end
  end

  defp request({_bus, _address}, commands, timeout) when is_list(commands) and commands != [] do
    # every command must encode (a bad one raises here, in the caller); the caller's last
    # request is remembered, so a poll sent again and again is encoded here only once
    unless Process.get({__MODULE__, :checked}) == commands do
      Enum.each(commands, &Vws.Codecs.SCPI.encode_command/1)
      Process.put({__MODULE__, :checked}, commands)
    end

    timeout = timeout && max(timeout, 0)
    {{:request, commands, timeout}, timeout || @default_wait}
  end
end
