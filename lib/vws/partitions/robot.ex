defmodule Vws.Partitions.Robot do
  @moduledoc """
  ROBOT: the partition that runs the robot command set (seed App. I) on the VAL II.

  Until its device link is configured every valid command ends `ERROR NO LINK TO VAL II`.
  """
  @behaviour Vws.Partition

  @impl true
  def device, do: "VAL II"

  @impl true
  def parse(text), do: Vws.Commands.parse(:robot, text)

  @impl true
  def execute(_command, _ctx), do: {:error, "NO LINK TO VAL II"}
end
