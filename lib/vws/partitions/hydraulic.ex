defmodule Vws.Partitions.Hydraulic do
  @moduledoc """
  HYDRAULIC: the partition that runs the hydraulic command set (seed App. I) on the HYDRAULIC CONTROLLER.

  Until its device link is configured every valid command ends `ERROR NO LINK TO HYDRAULIC CONTROLLER`.
  """
  @behaviour Vws.Partition

  @impl true
  def device, do: "HYDRAULIC CONTROLLER"

  @impl true
  def parse(text), do: Vws.Commands.parse(:hydraulic, text)

  @impl true
  def execute(_command, _ctx), do: {:error, "NO LINK TO HYDRAULIC CONTROLLER"}
end
