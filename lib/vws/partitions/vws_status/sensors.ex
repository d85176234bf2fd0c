defmodule Vws.Partitions.VwsStatus.Sensors do
  @moduledoc """
  What VWS_STATUS knows of DAQ #1's sensors and relays, as plain functions (no process, no
  mailbox): which mailbox locations hold its texts and readings and what they hold when there is
  no fresh reading, how the reading kept in location 11 reads, the values of signals for a
  partition's check, the tray locks' relays and switches, relay names, and how an HPIB answer
  reads as a command status.

  `Vws.Partitions.VwsStatus` polls and actuates with them; GRIPPER, FIXTURE and VACUUM check
  what their commands did with `values/3`.

      iex> alias Vws.Partitions.VwsStatus.Sensors
      iex> Sensors.reading({:no_data, "DAQ #1 NOT ANSWERING"})
      {:no_data, "DAQ #1 NOT ANSWERING"}
      iex> Sensors.reading(nil)
      {:no_data, "DAQ #1 NOT READ YET"}
      iex> r = %Vws.Links.DAQ.Readings{values: %{vacuum_on: :open_circuit}, channels: %{vacuum_on: 112}}
      iex> Sensors.values(r, [:vacuum_on], "VACUUM")
      {:wait, "VACUUM SENSOR CH 112 OPEN CIRCUIT"}
      iex> Sensors.values(r, [:vise_jaw_mm], "VISE")
      {:fail, "VISE SENSOR VISE_JAW_MM NOT WIRED"}
      iex> Sensors.relay_name(:cycle_start_relay)
      "CYCLE_START_RELAY"
  """

  alias Vws.Links.{DAQ, HPIB}
  alias Vws.Links.DAQ.{DeviceStatus, Readings}

  @device "DAQ #1"
  # relays wired as push buttons: pressed briefly, never to stay closed
  @buttons [:cycle_start_relay]
  @text_locations [1, 2, 3, 4, 5, 7]
  @sensors_location 11
  # Locations written by another partition: {location, its device, the `devices:` key of its link}
  @other_locations [
    {6, "GE-2000", :ge2000},
    {8, "GE-2000", :ge2000},
    {9, "VAL II", :robot},
    {10, "HYDRAULIC CONTROLLER", :hydraulic}
  ]

  @doc "The device's name in texts: `DAQ #1`."
  @spec device() :: String.t()
  def device, do: @device

  @doc "The locations VWS_STATUS keeps: the device texts (1–5, 7) and the readings (11)."
  @spec locations() :: [pos_integer]
  def locations, do: @text_locations ++ [@sensors_location]

  @doc "The location of the readings themselves (`SENSORS`)."
  @spec sensors_location() :: 11
  def sensors_location, do: @sensors_location

  @doc """
  What every location VWS_STATUS keeps holds when there is no fresh reading: `[{location,
  value}]`, the texts `NO DATA (<why>)` and the readings `{:no_data, why}`.
  """
  @spec no_data(String.t()) :: [{pos_integer, String.t() | {:no_data, String.t()}}]
  def no_data(why),
    do:
      for(loc <- @text_locations, do: {loc, DeviceStatus.no_data(why)}) ++
        [{@sensors_location, {:no_data, why}}]

  @doc """
  What the locations of the other devices (MONARCH and TLI_TABLE, WHERE_ROBOT, PALLET) say until
  their partitions write them: `[{location, text}]`, by whether their link is among
  `configured` (the `devices:` keys) — `NOT READ YET` — or not — `NO LINK TO <device>`.
  """
  @spec other_locations([atom]) :: [{pos_integer, String.t()}]
  def other_locations(configured) do
    for {loc, device, key} <- @other_locations do
      why = if key in configured, do: "#{device} NOT READ YET", else: "NO LINK TO #{device}"
      {loc, DeviceStatus.no_data(why)}
    end
  end

  @doc """
  The readings as location 11 holds them: `{:ok, readings}`, or `{:no_data, why}` when there
  are none or they went stale.
  """
  @spec reading(term) :: {:ok, Readings.t()} | {:no_data, String.t()}
  def reading(%Readings{} = r), do: {:ok, r}
  def reading({:no_data, why}), do: {:no_data, why}
  def reading(_other), do: {:no_data, "#{@device} NOT READ YET"}

  @doc """
  The values of `signals` in one reading, for a `check` of `Vws.Partitions.VwsStatus.await/4`:
  `{:ok, values}`, or the verdict when one cannot be read — `{:wait, "<DEVICE> SENSOR CH nnn OPEN
  CIRCUIT"}` (it may come back), `{:fail, "<DEVICE> SENSOR <SIGNAL> NOT WIRED"}` (it never will).
  """
  @spec values(Readings.t(), [atom], String.t()) ::
          {:ok, [Readings.value()]} | {:wait, String.t()} | {:fail, String.t()}
  def values(r, signals, device) do
    case Readings.fetch(r, signals) do
      {:ok, values} -> {:ok, values}
      {:open_circuit, ch} -> {:wait, "#{device} SENSOR CH #{ch} OPEN CIRCUIT"}
      {:not_wired, signal} -> {:fail, "#{device} SENSOR #{relay_name(signal)} NOT WIRED"}
    end
  end

  @doc "A signal's or relay's name as a text shows it: `:tray1_lock` → `TRAY1_LOCK`, 206 → `206`."
  @spec relay_name(atom | pos_integer) :: String.t()
  def relay_name(relay) when is_atom(relay), do: relay |> to_string() |> String.upcase()
  def relay_name(relay), do: to_string(relay)

  @doc "The push buttons this DAQ's channel map has (`Vws.Links.DAQ.new/1` options)."
  @spec buttons(keyword) :: MapSet.t(atom)
  def buttons(daq_opts) do
    daq = DAQ.new(daq_opts)

    for b <- @buttons,
        match?({:ok, _, _}, DAQ.actuation(daq, [{b, :open}])),
        into: MapSet.new(),
        do: b
  end

  @doc """
  A tray's lock: the relay to set and the action (`:close` to lock), and the check of its
  lock-pin switch for `Vws.Partitions.VwsStatus.await/4`.
  """
  @spec tray_lock(1 | 2, :lock | :release | :unlock) ::
          {{atom, :open | :close}, (Readings.t() -> :ok | {:wait, String.t()})}
  def tray_lock(tray, how) when tray in [1, 2] and how in [:lock, :release, :unlock] do
    relay = if tray == 1, do: :tray1_lock, else: :tray2_lock
    switch = if tray == 1, do: :tray1_locked, else: :tray2_locked
    locked? = how == :lock

    check = fn r ->
      case Readings.get(r, switch) do
        ^locked? -> :ok
        :open_circuit -> {:wait, "TRAY #{tray} LOCK SWITCH OPEN CIRCUIT"}
        _ when locked? -> {:wait, "TRAY #{tray} LOCK PIN NOT ENGAGED"}
        _ -> {:wait, "TRAY #{tray} LOCK PIN NOT RELEASED"}
      end
    end

    {{relay, if(locked?, do: :close, else: :open)}, check}
  end

  @doc """
  Why the readings are stale, from the last poll's error (`polling?`: a poll is still
  unanswered; `stale`: the reason shown now, if any).
  """
  @spec stale_reason(HPIB.Error.t() | nil, boolean, String.t() | nil) :: String.t()
  def stale_reason(last_error, polling?, stale) do
    case last_error do
      _ when polling? -> "#{@device} NOT ANSWERING"
      %HPIB.Error{reason: :timeout} -> "#{@device} NOT ANSWERING"
      %HPIB.Error{reason: :not_connected, detail: :timeout} -> "#{@device} NOT ANSWERING"
      %HPIB.Error{reason: :bad_response} -> "#{@device} BAD ANSWER"
      %HPIB.Error{} -> "#{@device} NOT CONNECTED"
      nil -> stale || "#{@device} NOT ANSWERING"
    end
  end

  @doc """
  How an actuation's answer reads: `:ok` when the relays read back as `expected`; `{:next,
  commands, expected}` after the reads before a write, the write to send (`DAQ.confirm_relays/3`); `{:error,
  {:relays, why, results}}` when some do not, `{:error, {:damaged, why}}` when the answer was
  damaged or missing (the writes may have been done), `{:error, why}` for any other failure.
  """
  @spec actuation_result({:ok, [term]} | {:error, HPIB.Error.t()}, term) ::
          :ok
          | {:next, [Vws.Codecs.SCPI.command()], DAQ.expected()}
          | {:error, String.t() | {:relays, String.t(), [term]} | {:damaged, String.t()}}
  def actuation_result({:ok, results}, expected) do
    with {:error, why} <- DAQ.confirm_relays(expected, results, @device),
         do: {:error, {:relays, why, results}}
  end

  def actuation_result({:error, %HPIB.Error{reason: reason} = error}, _expected)
      when reason in [:bad_response, :timeout],
      do: {:error, {:damaged, hpib_reason(error)}}

  def actuation_result({:error, error}, _expected), do: {:error, hpib_reason(error)}

  @doc "An HPIB error as a command status shows it."
  @spec hpib_reason(HPIB.Error.t()) :: String.t()
  def hpib_reason(%HPIB.Error{} = error), do: HPIB.Error.status_reason(error, @device)
end
