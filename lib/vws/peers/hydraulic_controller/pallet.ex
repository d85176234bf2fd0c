defmodule Vws.Peers.HydraulicController.Pallet do
  @moduledoc """
  What the hydraulic controller does on DAQ #2 (seed §5, App. I F): the pallet's two positioning
  rams and two swing ("swivel-rocker") clamps, driven through the relays of DAQ #2's slot 2 and
  checked on its X/Y microswitches and clamp-force gauges (channel map: the `daq2` unit of
  `priv/plant.exs`, read with `Vws.Links.DAQ`).

  Each operation is a list of steps run in order, every one confirmed by the sensors — on two
  readings in a row, as one may be damaged on the line — before the next starts (seed §6,
  hardware handshaking); the first step that is not confirmed within
  `:step_timeout_ms` ends it with what was measured:

    * `clamp_pallet/1` — X ram out, until the pallet is against its X stop
      (`PALLET NOT AGAINST X STOP`); Y ram out, until it is against its Y stop too
      (`PALLET NOT AGAINST Y STOP`); clamp 1 on, until its force reaches `:min_force_n`
      (`CLAMP 1 FORCE 1200 N BELOW 4000 N`); clamp 2 the same; then all four checked once more.
    * `release_pallet/1` — the reverse: clamp 2 off, until its force is below `:released_n`
      (`CLAMP 2 NOT RELEASED (FORCE 5000 N)`); clamp 1 the same; Y ram in, until the Y switch
      opens (`PALLET STILL AGAINST Y STOP`); X ram in likewise.
    * `depressurise/1` — the seed's third initialisation routine: every valve relay open at once,
      then both clamp forces below `:released_n`.

  A step that fails leaves the valves as they are, so `PALLET?` shows the real state and the
  CEC decides the recovery (usually RELEASE_PALLET). Relays are confirmed with `ROUT:CLOS?`
  and the whole slot read back after every write: a relay not as intended is set right (twice at
  most) and otherwise ends the operation (`RELAY 203 NOT AS COMMANDED`);
  a DAQ #2 reading that cannot be had is asked again until the step's time is up, then it is the
  reason (`DAQ #2 NOT ANSWERING (NO ANSWER IN 500 MS)`); a sensor that reads open circuit is waited
  for and reported (`CLAMP 1 FORCE GAUGE OPEN CIRCUIT (DAQ #2 CH 103)`).

  The functions block (each step polls DAQ #2 every `:poll_ms`): the controller runs them in a
  process of their own, so it answers `STATUS?` meanwhile.

      iex> p = Vws.Peers.HydraulicController.Pallet.new({"doc-bus", 9})
      iex> {p.min_force_n, p.released_n}
      {4000.0, 200.0}
      iex> Vws.Peers.HydraulicController.Pallet.state(p, %{pallet_x: true, pallet_y: true,
      ...>   clamp1_force_n: 5012.0, clamp2_force_n: 4990.0})
      %{clamped: true, x: true, y: true, force1_n: 5012.0, force2_n: 4990.0}
  """

  alias Vws.Links.{DAQ, HPIB}
  alias Vws.Links.DAQ.Readings

  @device "DAQ #2"
  @overload 9.9e37

  @defaults [
    min_force_n: 4000,
    released_n: 200,
    step_timeout_ms: 5_000,
    poll_ms: 20,
    timeout_ms: 500
  ]

  @type t :: %__MODULE__{
          device: HPIB.device(),
          daq: DAQ.t(),
          min_force_n: float,
          released_n: float,
          step_timeout_ms: non_neg_integer,
          poll_ms: pos_integer,
          timeout_ms: pos_integer
        }
  @type result :: :done | {:error, String.t()}

  defstruct [:device, :daq, :min_force_n, :released_n, :step_timeout_ms, :poll_ms, :timeout_ms]

  @doc """
  The pallet on DAQ #2 at HPIB `device`. Options: `:min_force_n` (a clamp holds the pallet from
  this force on, default 4000 N of the 5000 N a swing clamp builds), `:released_n` (a clamp is
  released below this, default 200 N: the gauges' noise is ±25 N), `:step_timeout_ms` (5000),
  `:poll_ms` (20), `:timeout_ms` (one DAQ #2 request, 500), `:channel_map` (`Vws.Links.DAQ.new/1`).
  """
  @spec new(HPIB.device(), keyword) :: t
  def new(device, opts \\ []) do
    opts = Keyword.merge(@defaults, opts)

    %__MODULE__{
      device: device,
      daq: DAQ.new([daq: :daq2] ++ Keyword.take(opts, [:channel_map])),
      min_force_n: opts[:min_force_n] * 1.0,
      released_n: opts[:released_n] * 1.0,
      step_timeout_ms: opts[:step_timeout_ms],
      poll_ms: opts[:poll_ms],
      timeout_ms: opts[:timeout_ms]
    }
  end

  @doc """
  Identifies DAQ #2 (`*IDN?`) and clears its error queue (`*CLS`): the seed's second
  initialisation routine, once its HPIB device is connected. `:ok` or `{:error, reason}`.
  """
  @spec identify(t) :: :ok | {:error, String.t()}
  def identify(p) do
    with {:ok, [%{model: _}, :ok]} <- transaction(p, [:idn?, :cls]), do: :ok
  end

  @doc "Reads the X/Y switches and both forces once: the answer to `PALLET?`."
  @spec read(t) :: {:ok, Vws.Codecs.SCPI.pallet()} | {:error, String.t()}
  def read(p) do
    with {:ok, r} <- readings(p), do: {:ok, state(p, r.values)}
  end

  @doc """
  The `PALLET?` answer for sensor values (`Vws.Links.DAQ.Readings` `values`): clamped when the pallet
  is against both stops and both forces are at least `:min_force_n`. A force that cannot be read
  is reported as the overload value, a switch that cannot be read as open.
  """
  @spec state(t, map) :: Vws.Codecs.SCPI.pallet()
  def state(p, values) do
    x = values[:pallet_x] == true
    y = values[:pallet_y] == true
    f1 = force(values[:clamp1_force_n])
    f2 = force(values[:clamp2_force_n])
    clamped = x and y and f1 >= p.min_force_n and f2 >= p.min_force_n and max(f1, f2) < @overload
    %{clamped: clamped, x: x, y: y, force1_n: f1, force2_n: f2}
  end

  defp force(n) when is_number(n), do: n * 1.0
  defp force(_open_circuit_or_missing), do: @overload

  @doc "The answer to `PALLET?` when DAQ #2 cannot be read: not clamped, nothing confirmed."
  @spec unknown() :: Vws.Codecs.SCPI.pallet()
  def unknown, do: %{clamped: false, x: false, y: false, force1_n: @overload, force2_n: @overload}

  @doc "CLAMP_PALLET: rams X then Y, then clamps 1 and 2, each confirmed; see the moduledoc."
  @spec clamp_pallet(t) :: result
  def clamp_pallet(p) do
    run(p, [
      {[ram_x_valve: :close], [:x_stop]},
      {[ram_y_valve: :close], [:x_stop, :y_stop]},
      {[swing_clamp1_valve: :close], [:x_stop, :y_stop, {:clamped, 1}]},
      {[swing_clamp2_valve: :close], [:x_stop, :y_stop, {:clamped, 1}, {:clamped, 2}]}
    ])
  end

  @doc "RELEASE_PALLET: clamps 2 then 1 released, then rams Y and X retracted, each confirmed."
  @spec release_pallet(t) :: result
  def release_pallet(p) do
    run(p, [
      {[swing_clamp2_valve: :open], [{:released, 2}]},
      {[swing_clamp1_valve: :open], [{:released, 1}, {:released, 2}]},
      {[ram_y_valve: :open], [:y_clear]},
      {[ram_x_valve: :open], [:y_clear, :x_clear]}
    ])
  end

  @doc "Depressurise: every valve relay open, then both clamps confirmed released."
  @spec depressurise(t) :: result
  def depressurise(p) do
    valves = [:swing_clamp2_valve, :swing_clamp1_valve, :ram_y_valve, :ram_x_valve]
    run(p, [{Enum.map(valves, &{&1, :open}), [{:released, 1}, {:released, 2}]}])
  end

  ## Steps

  defp run(p, steps) do
    Enum.reduce_while(steps, :done, fn {actions, checks}, :done ->
      with :ok <- actuate(p, actions),
           :ok <- await(p, checks) do
        {:cont, :done}
      else
        {:error, _} = error -> {:halt, error}
      end
    end)
  end

  # The whole slot is read back after every write (PROTOCOLS.md §4); a relay of it not as
  # intended — the commanded one or any other — is set right and the slot read again, at most
  # twice (the command or its answer may have been damaged on the line).
  defp actuate(p, actions) do
    with {:ok, commands, expected} <- actuation(p, actions),
         do: confirm(p, commands, expected, 3)
  end

  defp confirm(p, commands, expected, tries) do
    case HPIB.transaction(p.device, commands, p.timeout_ms) do
      {:ok, results} ->
        confirmed(p, expected, tries, results)

      # the answers still damaged (or missing) after the bus's own tries: the writes may have
      # been done, so the slot is read again and set right only where it is not as intended
      {:error, %HPIB.Error{reason: reason}} when reason in [:bad_response, :timeout] and tries > 1 ->
        confirm(p, DAQ.recheck(expected), expected, tries - 1)

      {:error, error} ->
        {:error, hpib_reason(error)}
    end
  end

  defp confirmed(p, expected, tries, results) do
    case DAQ.confirm_relays(expected, results, @device) do
      # the slot read before the write: the write goes out, in the same try
      {:next, commands, expected} ->
        confirm(p, commands, expected, tries)

      {:error, _} when tries > 1 ->
        Vws.Telemetry.execute([:vws, :hydraulic_controller, :relay_corrected], %{count: 1}, %{
          device: p.device
        })

        {:ok, commands, expected} = DAQ.correction(expected, results)
        confirm(p, commands, expected, tries - 1)

      result ->
        result
    end
  end

  defp actuation(p, actions) do
    case DAQ.actuation(p.daq, actions) do
      {:ok, _commands, _expected} = ok ->
        ok

      {:error, {:unknown_actuator, signal}} ->
        {:error, "#{signal |> to_string() |> String.upcase()} NOT WIRED TO #{@device}"}
    end
  end

  defp transaction(p, commands) do
    case HPIB.transaction(p.device, commands, p.timeout_ms) do
      {:ok, results} -> {:ok, results}
      {:error, error} -> {:error, hpib_reason(error)}
    end
  end

  # Polls DAQ #2 until every check holds; at the deadline, the first one that did not is the
  # reason, with what it read.
  # A step is confirmed by two readings in a row (one damaged on the line confirms nothing); a
  # reading that cannot be had is tried again until the deadline, then it is the reason.
  defp await(p, checks) do
    deadline = System.monotonic_time(:millisecond) + p.step_timeout_ms
    do_await(p, checks, deadline, false)
  end

  defp do_await(p, checks, deadline, held_once?) do
    verdict =
      case readings(p) do
        {:ok, r} -> Enum.find_value(checks, &failing(p, &1, r))
        {:error, why} -> {:unread, why}
      end

    cond do
      verdict == nil and held_once? ->
        :ok

      verdict == nil ->
        # held: one more reading to confirm it, the deadline notwithstanding
        Process.sleep(p.poll_ms)
        do_await(p, checks, deadline, true)

      System.monotonic_time(:millisecond) >= deadline ->
        {:error, with({:unread, why} <- verdict, do: why)}

      true ->
        Process.sleep(p.poll_ms)
        do_await(p, checks, deadline, false)
    end
  end

  # nil when the check holds, else what was read, as the error reason says it.
  defp failing(p, check, r) do
    case check do
      :x_stop -> switch(r, :pallet_x, true, "PALLET NOT AGAINST X STOP")
      :y_stop -> switch(r, :pallet_y, true, "PALLET NOT AGAINST Y STOP")
      :x_clear -> switch(r, :pallet_x, false, "PALLET STILL AGAINST X STOP")
      :y_clear -> switch(r, :pallet_y, false, "PALLET STILL AGAINST Y STOP")
      {:clamped, n} -> gauge(r, n, &(&1 >= p.min_force_n), "BELOW #{newtons(p.min_force_n)} N")
      {:released, n} -> gauge(r, n, &(&1 < p.released_n), nil)
    end
  end

  defp switch(r, signal, want, why) do
    case Readings.get(r, signal) do
      ^want -> nil
      :open_circuit -> "#{switch_name(signal)} SWITCH OPEN CIRCUIT (#{channel(r, signal)})"
      nil -> "#{switch_name(signal)} SWITCH NOT WIRED TO #{@device}"
      _ -> why
    end
  end

  defp gauge(r, n, ok?, below) do
    signal = if n == 1, do: :clamp1_force_n, else: :clamp2_force_n

    case Readings.get(r, signal) do
      :open_circuit ->
        "CLAMP #{n} FORCE GAUGE OPEN CIRCUIT (#{channel(r, signal)})"

      nil ->
        "CLAMP #{n} FORCE GAUGE NOT WIRED TO #{@device}"

      force ->
        cond do
          ok?.(force) -> nil
          below -> "CLAMP #{n} FORCE #{newtons(force)} N #{below}"
          true -> "CLAMP #{n} NOT RELEASED (FORCE #{newtons(force)} N)"
        end
    end
  end

  defp switch_name(:pallet_x), do: "PALLET X"
  defp switch_name(:pallet_y), do: "PALLET Y"
  defp channel(r, signal), do: "#{@device} CH #{Readings.channel(r, signal)}"

  defp readings(p) do
    with {:ok, answers} <- transaction(p, DAQ.poll_commands(p.daq)),
         do: {:ok, DAQ.readings(p.daq, answers)}
  end

  @doc "Newtons as the error texts write them: a whole number, never negative."
  @spec newtons(number) :: String.t()
  def newtons(value), do: Vws.Links.DAQ.DeviceStatus.newtons(value)

  @doc "An HPIB error on the link to DAQ #2, as a status reason."
  @spec hpib_reason(HPIB.Error.t()) :: String.t()
  def hpib_reason(%HPIB.Error{} = error), do: HPIB.Error.status_reason(error, @device)
end
