defmodule Vws.Partitions.Gripper do
  @moduledoc """
  GRIPPER (seed App. I D): opens and closes the robot gripper's fingers and turns its rotary
  indexer, through the actuators of DAQ #1 (`Vws.Partitions.VwsStatus.operate/4`), and ends each
  command `DONE` only once the sensors confirm it (seed §6, hardware handshaking):

    * `OPEN` — OPEN solenoid on, CLOSE solenoid off; done when the fully-open switch closes.
      Else `ERROR GRIPPER DID NOT OPEN (FINGERS d MM APART)`.
    * `CLOSE` — CLOSE solenoid on, OPEN off; the fingers close "until it stops against an object
      or against its own fingers (empty)": done when they have left the open stop and stand
      still (two readings within 0.5 mm). Closing on nothing is therefore `DONE`, and the
      `GRIPPER` status then shows the fingers 0.0 mm apart. Else `ERROR GRIPPER DID NOT CLOSE
      (FINGERS d MM APART)`.
    * `ROTATE_n` — the indexer select bits to n/90; done when exactly the position switch of n
      degrees is closed. Else `ERROR INDEXER DID NOT REACH n DEG (AT m DEG | BETWEEN POSITIONS |
      SWITCHES DISAGREE)`.

  A sensor reading open circuit ends the command `ERROR GRIPPER SENSOR CH nnn OPEN CIRCUIT`; a
  DAQ that does not answer, `ERROR DAQ #1 NOT ANSWERING (…)`.

  Options (`ctx.options`): `:timeout_ms` — how long the sensors have to confirm (default 3000
  for OPEN and CLOSE, 6000 for ROTATE_n, a 270° turn taking 3 s).
  """
  @behaviour Vws.CEC.Partition.CommandSet

  alias Vws.Links.DAQ.{DeviceStatus, Readings}
  alias Vws.Partitions.VwsStatus

  @still_mm 0.5

  @impl true
  def device, do: "DAQ #1"

  @impl true
  def parse(text), do: Vws.Codecs.Commands.parse(:gripper, text)

  @impl true
  def execute(:open, ctx) do
    actions = [gripper_close_solenoid: :open, gripper_open_solenoid: :close]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx, 3_000), fn r ->
      with {:ok, [open, mm]} <-
             VwsStatus.Sensors.values(r, [:gripper_fully_open, :gripper_finger_mm], "GRIPPER") do
        if open,
          do: :ok,
          else: {:wait, "GRIPPER DID NOT OPEN (FINGERS #{DeviceStatus.mm(mm)} MM APART)"}
      end
    end)
  end

  def execute(:close, ctx) do
    actions = [gripper_open_solenoid: :open, gripper_close_solenoid: :close]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx, 3_000), fn r, prev ->
      with {:ok, [open, mm]} <-
             VwsStatus.Sensors.values(r, [:gripper_fully_open, :gripper_finger_mm], "GRIPPER") do
        still? =
          case prev && Readings.get(prev, :gripper_finger_mm) do
            before when is_float(before) -> abs(before - mm) <= @still_mm
            _ -> false
          end

        if not open and still?,
          do: :ok,
          else: {:wait, "GRIPPER DID NOT CLOSE (FINGERS #{DeviceStatus.mm(mm)} MM APART)"}
      end
    end)
  end

  def execute({:rotate, deg}, ctx) do
    position = div(deg, 90)

    actions = [
      indexer_bit0: if(rem(position, 2) == 1, do: :close, else: :open),
      indexer_bit1: if(position >= 2, do: :close, else: :open)
    ]

    switches = [:indexer_0, :indexer_90, :indexer_180, :indexer_270]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx, 6_000), fn r ->
      with {:ok, _states} <- VwsStatus.Sensors.values(r, switches, "GRIPPER") do
        case DeviceStatus.indexer(r) do
          {:ok, ^deg} -> :ok
          {:ok, other} -> {:wait, "INDEXER DID NOT REACH #{deg} DEG (AT #{other} DEG)"}
          {:error, :between} -> {:wait, "INDEXER DID NOT REACH #{deg} DEG (BETWEEN POSITIONS)"}
          {:error, :disagree} -> {:wait, "INDEXER DID NOT REACH #{deg} DEG (SWITCHES DISAGREE)"}
        end
      end
    end)
  end

  defp timeout(ctx, default), do: Keyword.get(ctx.options, :timeout_ms, default)
end
