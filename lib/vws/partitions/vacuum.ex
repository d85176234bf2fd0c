defmodule Vws.Partitions.Vacuum do
  @moduledoc """
  VACUUM (seed App. I C): runs the chip-removal vacuum's motor through a relay of DAQ #1
  (`Vws.Partitions.VwsStatus.operate/4`) and ends each command `DONE` only once the vacuum's
  pressure switch confirms it:

    * `ON` — motor relay closed; done when the pressure switch closes. Else
      `ERROR VACUUM DID NOT TURN ON (PRESSURE SWITCH OPEN)`.
    * `OFF` — motor relay open; done when the pressure switch opens. Else
      `ERROR VACUUM DID NOT TURN OFF (PRESSURE SWITCH CLOSED)`.

  Options (`ctx.options`): `:timeout_ms` (default 3000).
  """
  @behaviour Vws.CEC.Partition.CommandSet

  alias Vws.Partitions.VwsStatus

  @impl true
  def device, do: "DAQ #1"

  @impl true
  def parse(text), do: Vws.Codecs.Commands.parse(:vacuum, text)

  @impl true
  def execute(command, ctx) when command in [:on, :off] do
    on? = command == :on
    action = if on?, do: :close, else: :open
    timeout = Keyword.get(ctx.options, :timeout_ms, 3_000)

    VwsStatus.operate(ctx.workstation, [vacuum_motor: action], timeout, fn r ->
      case VwsStatus.Sensors.values(r, [:vacuum_on], "VACUUM") do
        {:ok, [^on?]} -> :ok
        {:ok, [_]} when on? -> {:wait, "VACUUM DID NOT TURN ON (PRESSURE SWITCH OPEN)"}
        {:ok, [_]} -> {:wait, "VACUUM DID NOT TURN OFF (PRESSURE SWITCH CLOSED)"}
        verdict -> verdict
      end
    end)
  end
end
