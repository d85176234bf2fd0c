defmodule Vws.Sim.DAQ do
  @moduledoc """
  A simulated data-acquisition unit (PROTOCOLS.md §4: the SCPI of a 34970A/DAQ970A standing in
  for the seed's HP 3497A) on its own endpoint, wired to the channels of a `Vws.Sim.Plant`.

  It listens like a LAN instrument's raw SCPI socket (default `tcp://127.0.0.1:0`, a free port:
  see `endpoint/1`), serves any number of connections, and answers each line in order:

  | command | effect |
  |---------|--------|
  | `*IDN?` | `NBS-VWS-SIM,34970A,<daq>,1.0` |
  | `*RST` | opens every relay of this DAQ; empties the error queue |
  | `*CLS` | empties the error queue |
  | `SYST:ERR?` | the oldest queued error, `+0,"No error"` when none |
  | `MEAS:VOLT:DC? (@…)`, `MEAS:RES? (@…)` | the plant's readings, with its noise |
  | `ROUT:CLOS (@…)`, `ROUT:OPEN (@…)` | relays of the plant's actuator channels |
  | `ROUT:CLOS? (@…)` | `1`/`0` per channel |

  As a real instrument does, a line it cannot parse, or one naming a channel that is not a
  sensor (for a measurement) or not a relay (for a route), is not executed and not answered: an
  SCPI error goes on the error queue (at most 20; then `-350,"Queue overflow"`) for `SYST:ERR?`.

      iex> {:ok, plant} = Vws.Sim.Plant.start_link(time_scale: 0)
      iex> {:ok, daq} = Vws.Sim.DAQ.start_link(plant: plant)
      iex> Vws.Sim.DAQ.endpoint(daq) =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
      iex> {:ok, conn} = Vws.Links.Transport.connect(Vws.Sim.DAQ.endpoint(daq))
      iex> :ok = Vws.Links.Transport.send(conn, "ROUT:CLOS (@207)\\nROUT:CLOS? (@207)\\n")
      iex> :ok = Vws.Links.Transport.activate(conn)
      iex> receive do msg -> Vws.Links.Transport.handle_message(conn, msg) end
      {:data, "1\\n"}

  ## Faults of the instrument itself

  `set_fault/2` makes it misbehave the way a hung or slow instrument does (the plant's own faults
  are injected into the plant): `:mute` — it takes every line and neither executes nor answers
  anything; `{:delay_ms, n}` — it answers each line n ms late; `:none` — healthy again.
  """
  use GenServer
  require Logger

  alias Vws.Codecs.SCPI
  alias Vws.Links.Transport
  alias Vws.Sim.Plant

  @max_errors 20
  @no_error {0, "No error"}
  @overflow {-350, "Queue overflow"}
  @settings_conflict {-221, "Settings conflict"}
  @undefined_header {-113, "Undefined header"}

  @type fault :: :none | :mute | {:delay_ms, non_neg_integer}

  @doc false
  def child_spec(opts) do
    %{id: {__MODULE__, Keyword.get(opts, :name)}, start: {__MODULE__, :start_link, [opts]}}
  end

  @doc """
  Starts a DAQ. Options: `:plant` (required), `:endpoint` to listen on (default
  `"tcp://127.0.0.1:0"`), `:daq` (`:daq1` or `:daq2`, default `:daq1`), `:name`, `:allow` (who
  may connect, `Vws.Links.Transport.Policy`; default loopback only).
  """
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    {name, opts} = Keyword.pop(opts, :name)
    GenServer.start_link(__MODULE__, opts, if(name, do: [name: name], else: []))
  end

  @doc "The endpoint it listens on, as a string (with the real port when port 0 was asked)."
  @spec endpoint(GenServer.server()) :: String.t()
  def endpoint(daq), do: GenServer.call(daq, :endpoint)

  @doc "Makes the instrument misbehave (`:mute`, `{:delay_ms, n}`) or heals it (`:none`)."
  @spec set_fault(GenServer.server(), fault) :: :ok
  def set_fault(daq, fault)
      when fault in [:none, :mute] or
             (is_tuple(fault) and elem(fault, 0) == :delay_ms and elem(fault, 1) >= 0),
      do: GenServer.call(daq, {:set_fault, fault})

  @doc "Closes every connection (as a power cycle does); it keeps listening."
  @spec drop_connections(GenServer.server()) :: :ok
  def drop_connections(daq), do: GenServer.call(daq, :drop_connections)

  @doc "Counters: `%{connections, lines, answered, errors, fault, queued_errors}`."
  @spec info(GenServer.server()) :: map
  def info(daq), do: GenServer.call(daq, :info)

  ## Server

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    # The simulated DAQ (and its plant) stand in for equipment with a processor of its own: they
    # run ahead of the node's normal work, so that a loaded node (a full test suite on two
    # cores) does not make the instrument answer late. Each request is a few microseconds.
    Process.flag(:priority, :high)
    plant = Keyword.fetch!(opts, :plant)
    daq = Keyword.get(opts, :daq, :daq1)

    case Transport.listen(Keyword.get(opts, :endpoint, "tcp://127.0.0.1:0")) do
      {:ok, listener} ->
        acceptor =
          Transport.start_acceptor(listener, self(), :accepted,
            allow: Vws.Links.Transport.Policy.parse_allow!(Keyword.get(opts, :allow))
          )

        {:ok,
         %{
           plant: plant,
           daq: daq,
           listener: listener,
           acceptor: acceptor,
           conns: %{},
           errors: :queue.new(),
           fault: :none,
           counts: %{connections: 0, lines: 0, answered: 0, errors: 0}
         }}

      {:error, reason} ->
        {:stop, {:cannot_listen, reason}}
    end
  end

  @impl true
  def handle_call(:endpoint, _from, s),
    do: {:reply, to_string(Transport.listener_endpoint(s.listener)), s}

  def handle_call({:set_fault, fault}, _from, s), do: {:reply, :ok, %{s | fault: fault}}

  def handle_call(:drop_connections, _from, s) do
    Enum.each(s.conns, fn {_key, %{conn: conn}} -> Transport.close(conn) end)
    {:reply, :ok, %{s | conns: %{}}}
  end

  def handle_call(:info, _from, s) do
    info = Map.merge(s.counts, %{fault: s.fault, queued_errors: :queue.len(s.errors), daq: s.daq})

    {:reply, info, s}
  end

  @impl true
  def handle_info({:accepted, conn}, s) do
    :ok = Transport.activate(conn)
    key = make_ref()
    conns = Map.put(s.conns, key, %{conn: conn, decoder: SCPI.new()})
    {:noreply, %{s | conns: conns} |> count(:connections)}
  end

  def handle_info({:answer, key, bytes}, s) do
    case Map.fetch(s.conns, key) do
      {:ok, %{conn: conn}} -> _ = Transport.send(conn, bytes)
      :error -> :ok
    end

    {:noreply, s}
  end

  def handle_info({:EXIT, pid, reason}, %{acceptor: pid} = s),
    do: {:stop, {:acceptor_down, reason}, s}

  def handle_info({:EXIT, _pid, _reason}, s), do: {:noreply, s}

  def handle_info(msg, s) do
    case Enum.find_value(s.conns, fn {key, c} -> classify(key, c, msg) end) do
      {key, {:data, bytes}} ->
        %{conn: conn, decoder: decoder} = s.conns[key]
        :ok = Transport.activate(conn)
        {lines, decoder} = SCPI.feed(decoder, bytes)
        s = put_in(s.conns[key].decoder, decoder)
        {:noreply, Enum.reduce(lines, s, &serve_line(key, &1, &2))}

      {key, _closed_or_error} ->
        Transport.close(s.conns[key].conn)
        {:noreply, %{s | conns: Map.delete(s.conns, key)}}

      nil ->
        Logger.debug("Sim.DAQ: unexpected message #{inspect(msg, limit: 10)}")
        {:noreply, s}
    end
  end

  @impl true
  def terminate(_reason, s) do
    Enum.each(s.conns, fn {_key, %{conn: conn}} -> Transport.close(conn) end)
    Transport.close_listener(s.listener)
  end

  defp classify(key, %{conn: conn}, msg) do
    case Transport.handle_message(conn, msg) do
      :unknown -> nil
      result -> {key, result}
    end
  end

  ## One line

  defp serve_line(_key, _line, %{fault: :mute} = s), do: count(s, :lines)

  defp serve_line(key, line, s) do
    s = count(s, :lines)

    decoded =
      case line do
        {:error, error} -> {:error, error}
        text -> SCPI.decode_command(text)
      end

    case decoded do
      {:ok, command} ->
        {answer, s} = execute(command, s)
        if answer == :none, do: s, else: answer(key, SCPI.encode_response(answer), s)

      {:error, error} ->
        push_error(s, Vws.Codecs.SCPI.Error.scpi_error(error))
    end
  end

  defp answer(key, bytes, %{fault: {:delay_ms, ms}} = s) do
    Process.send_after(self(), {:answer, key, bytes}, ms)
    count(s, :answered)
  end

  defp answer(key, bytes, s) do
    _ = Transport.send(s.conns[key].conn, bytes)
    count(s, :answered)
  end

  defp execute(:idn?, s) do
    {%{manufacturer: "NBS-VWS-SIM", model: "34970A", serial: to_string(s.daq), firmware: "1.0"},
     s}
  end

  defp execute(:rst, s) do
    :ok = Plant.open_all(s.plant, s.daq)
    {:none, %{s | errors: :queue.new()}}
  end

  defp execute(:cls, s), do: {:none, %{s | errors: :queue.new()}}

  defp execute(:syst_err?, s) do
    case :queue.out(s.errors) do
      {{:value, entry}, rest} -> {entry, %{s | errors: rest}}
      {:empty, _} -> {@no_error, s}
    end
  end

  defp execute({:meas_volt_dc?, channels}, s), do: measure(&Plant.read_voltage/2, channels, s)
  defp execute({:meas_res?, channels}, s), do: measure(&Plant.read_resistance/2, channels, s)

  defp execute({:rout_clos?, channels}, s) do
    results = Enum.map(channels, &Plant.channel_closed?(s.plant, {s.daq, &1}))

    if Enum.all?(results, &match?({:ok, _}, &1)),
      do: {Enum.map(results, &elem(&1, 1)), s},
      else: {:none, push_error(s, @settings_conflict)}
  end

  defp execute({route, channels}, s) when route in [:rout_clos, :rout_open] do
    # all relays or none, as the instrument checks the list before it switches
    if Enum.all?(channels, &match?({:ok, _}, Plant.channel_closed?(s.plant, {s.daq, &1}))) do
      set = if route == :rout_clos, do: &Plant.close_channel/2, else: &Plant.open_channel/2
      Enum.each(channels, fn ch -> :ok = set.(s.plant, {s.daq, ch}) end)
      {:none, s}
    else
      {:none, push_error(s, @settings_conflict)}
    end
  end

  # CLAMP_PALLET and the other hydraulic-controller commands: not a DAQ's
  defp execute(_other, s), do: {:none, push_error(s, @undefined_header)}

  defp measure(read, channels, s) do
    results = Enum.map(channels, &read.(s.plant, {s.daq, &1}))

    if Enum.all?(results, &match?({:ok, _}, &1)),
      do: {Enum.map(results, &elem(&1, 1)), s},
      else: {:none, push_error(s, @settings_conflict)}
  end

  defp push_error(s, entry) do
    s = count(s, :errors)

    errors =
      if :queue.len(s.errors) >= @max_errors do
        {_, q} = :queue.out_r(s.errors)
        :queue.in(@overflow, q)
      else
        :queue.in(entry, s.errors)
      end

    %{s | errors: errors}
  end

  defp count(s, key), do: %{s | counts: Map.update!(s.counts, key, &(&1 + 1))}
end
