defmodule Vws.Partitions.Vacuum do
  @moduledoc """
  VACUUM: the partition that runs the vacuum command set (seed App. I) on the DAQ #1.

  Until its device link is configured every valid command ends `ERROR NO LINK TO DAQ #1`.
  """
  @behaviour Vws.Partition

  @impl true
  def device, do: "DAQ #1"

  @impl true
  def parse(text), do: Vws.Commands.parse(:vacuum, text)

  @impl true
  def execute(_command, _ctx), do: {:error, "NO LINK TO DAQ #1"}
end
