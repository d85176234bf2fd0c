defmodule Vws.Partitions.Fixture do
  @moduledoc """
  FIXTURE (seed App. I E, §2.3.8): opens and closes the vise through the valves of DAQ #1
  (`Vws.Partitions.VwsStatus.operate/4`), reads its clamping force, and takes the table's work
  volume for the vise (`Vws.CEC.Interlock`). Each vise command ends `DONE` only once the sensors
  confirm it (seed §6: "the clamping force exerted by the vise is sufficient to keep the
  workpiece from moving"):

    * `OPEN` — CLOSE valve off, OPEN valve on; done when the fully-open switch closes. Else
      `ERROR VISE DID NOT OPEN (JAWS d MM APART, FORCE f N)`.
    * `CLOSE` — OPEN valve off, CLOSE valve on; done when the part-present switch is closed, the
      force gauge reads at least `:min_force_n` (default 800 N) and the vise has come to rest (two
      fresh readings agree: jaws within 0.5 mm, force within 25 N — the force still rises past
      the minimum, and a machining cycle may not start while it does). Else, by what was read:
      `ERROR VISE FORCE 310 N BELOW 800 N` (a weak clamp), `ERROR PART NOT IN VISE (JAWS CLOSED
      TO 0.0 MM)` (an empty vise: the jaws close on their stop — this ends at once, nothing will
      change), `ERROR VISE DID NOT CLOSE (JAWS 150.0 MM APART)` (a stuck valve),
      `ERROR VISE FORCE 2000 N BUT PART NOT IN VISE` (the part switch disagrees).
    * `DISABLE_TABLE` / `RELEASE_TABLE` — take / give up the table's volume for the vise (seed
      Table 3: the table may not move while the vise opens or closes).

  A sensor reading open circuit ends the command `ERROR VISE SENSOR CH nnn OPEN CIRCUIT`; a DAQ
  that does not answer, `ERROR DAQ #1 NOT ANSWERING (…)`.

  ## Interlocks (seed §2.3.8 rules 3a, 3b)

  FIXTURE holds the `:table` volume as holder `:fixture`, shared with ROBOT (the robot holds the
  part while the vise closes on it) and never with MONARCH's cycle. The interlock table
  (`Vws.CEC.Interlock.Rules`) takes and gives back the lease around each command; this module
  gives the conditions (`conditions/2`) and the releases after a failure:

    * `OPEN` and `CLOSE` take it for the vise motion (reason `:vise`) before a valve moves, on the
      conditions of rule 3a — the machine idle and the table parked, as read
      (`Vws.Partitions.TableConditions.check/2`) — and give that reason up when the sensors confirm
      the vise at its end. A vise command that fails leaves the vise where the sensors cannot
      vouch for it: both valves are switched off (the vise holds) and the table stays held
      (rule 3b: no cycle may start) until a later `OPEN`/`CLOSE` succeeds or `RELEASE_TABLE`
      finds the vise at rest.
    * `DISABLE_TABLE` takes it (reason `:disabled`) on the same conditions; `RELEASE_TABLE`
      gives up everything FIXTURE holds — after two fresh readings show the vise at rest when a
      failed vise command left it held (else `ERROR VISE NOT AT REST (…)`).

  A request that times out ends `ERROR INTERLOCK TABLE HELD BY MONARCH` or
  `ERROR INTERLOCK TABLE <condition>`.

  Options (`ctx.options`): `:timeout_ms` (default 5000: a full stroke is 1.5 s, the force rise
  0.3 s), `:min_force_n`, `:interlock` (as ROBOT's: `timeout`, `retry_ms`, `machine_stale_ms`,
  `sensor_timeout_ms`).
  """
  @behaviour Vws.CEC.Partition.CommandSet

  alias Vws.CEC.Interlock
  alias Vws.Links.DAQ.DeviceStatus
  alias Vws.Partitions.VwsStatus

  @min_force_n 800
  # jaws this close together have closed on their own stop
  @closed_on_stop_mm 1.0
  # two readings this close: the vise is at rest (the noise is ±0.1 mm and ±5 N)
  @rest_mm 0.5
  @rest_n 25.0

  @doc "The noise bands within which two readings count as the same (mm, N): what the views deadband by."
  @spec noise_bands() :: %{mm: float, n: float}
  def noise_bands, do: %{mm: @rest_mm, n: @rest_n}

  @impl true
  def device, do: "DAQ #1"

  @impl true
  def parse(text), do: Vws.Codecs.Commands.parse(:fixture, text)

  @impl true
  def execute(:open, ctx), do: vise_motion(ctx, &open/1)
  def execute(:close, ctx), do: vise_motion(ctx, &close/1)

  # taken as :disabled by the interlock table (Vws.CEC.Interlock.Rules)
  def execute(:disable_table, _ctx), do: :done

  def execute(:release_table, ctx) do
    ws = ctx.workstation

    if Interlock.holds?(ws, :table, :fixture, :vise) do
      case at_rest(ctx) do
        :ok ->
          Interlock.release(ws, :table, :fixture)
          :done

        {:error, why} ->
          {:error, "VISE NOT AT REST (#{why})"}
      end
    else
      Interlock.release(ws, :table, :fixture)
      :done
    end
  end

  # After a restart that interrupted OPEN or CLOSE, or one after which FIXTURE's status is
  # unknown (a damaged journal: either may have been under way): both valves off, so the vise
  # holds where it is — what a failed motion leaves — never the motion again.
  @impl true
  def interrupted(command, ctx) when command in [:open, :close, :unknown] do
    VwsStatus.actuate(ctx.workstation, vise_open_valve: :open, vise_close_valve: :open)
  end

  def interrupted(_command, _ctx), do: :ok

  # The table is the vise's while it moves: the interlock table (Vws.CEC.Interlock.Rules) takes
  # it as :vise before a valve moves and gives that reason back when the motion ends DONE.
  defp vise_motion(ctx, motion) do
    case motion.(ctx) do
      :done ->
        :done

      error ->
        # both valves off: the vise holds where it is, whatever a valve does later
        _ = VwsStatus.actuate(ctx.workstation, vise_open_valve: :open, vise_close_valve: :open)
        error
    end
  end

  @doc "The conditions of rule 3a for the table (`Vws.Partitions.TableConditions`)."
  @impl true
  defdelegate conditions(volume, ctx), to: Vws.Partitions.TableConditions

  # Two fresh readings that agree.
  defp at_rest(ctx) do
    since = System.monotonic_time(:microsecond)

    VwsStatus.await(ctx.workstation, since, timeout(ctx), fn r, prev ->
      with {:ok, [jaw, force]} <-
             VwsStatus.Sensors.values(r, [:vise_jaw_mm, :vise_force_n], "VISE") do
        if rest?(prev, jaw, force),
          do: :ok,
          else: {:wait, "JAWS #{mm(jaw)} MM APART, FORCE #{n(force)} N"}
      end
    end)
  end

  defp rest?(nil, _jaw, _force), do: false

  defp rest?(prev, jaw, force) do
    case VwsStatus.Sensors.values(prev, [:vise_jaw_mm, :vise_force_n], "VISE") do
      {:ok, [jaw0, force0]} -> abs(jaw - jaw0) <= @rest_mm and abs(force - force0) <= @rest_n
      _ -> false
    end
  end

  defp open(ctx) do
    actions = [vise_close_valve: :open, vise_open_valve: :close]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx), fn r ->
      with {:ok, [open, jaw, force]} <-
             VwsStatus.Sensors.values(r, [:vise_fully_open, :vise_jaw_mm, :vise_force_n], "VISE") do
        if open,
          do: :ok,
          else: {:wait, "VISE DID NOT OPEN (JAWS #{mm(jaw)} MM APART, FORCE #{n(force)} N)"}
      end
    end)
  end

  defp close(ctx) do
    min = Keyword.get(ctx.options, :min_force_n, @min_force_n)
    actions = [vise_open_valve: :open, vise_close_valve: :close]
    signals = [:vise_part_present, :vise_fully_open, :vise_jaw_mm, :vise_force_n]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx), fn r, prev ->
      with {:ok, [part, open, jaw, force]} <- VwsStatus.Sensors.values(r, signals, "VISE") do
        cond do
          part and force >= min and rest?(prev, jaw, force) ->
            :ok

          part and force >= min ->
            {:wait, "VISE FORCE #{n(force)} N NOT STEADY"}

          force >= min ->
            {:wait, "VISE FORCE #{n(force)} N BUT PART NOT IN VISE"}

          not part and jaw < @closed_on_stop_mm ->
            {:fail, "PART NOT IN VISE (JAWS CLOSED TO #{mm(jaw)} MM)"}

          open ->
            {:wait, "VISE DID NOT CLOSE (JAWS #{mm(jaw)} MM APART)"}

          part ->
            {:wait, "VISE FORCE #{n(force)} N BELOW #{min} N"}

          true ->
            {:wait, "VISE DID NOT CLOSE (JAWS #{mm(jaw)} MM APART, FORCE #{n(force)} N)"}
        end
      end
    end)
  end

  defp timeout(ctx), do: Keyword.get(ctx.options, :timeout_ms, 5_000)
  defp mm(value), do: DeviceStatus.mm(value)
  defp n(value), do: DeviceStatus.newtons(value)
end
