defmodule Vws.Partitions.Monarch do
  @moduledoc """
  MONARCH: the partition that runs the monarch command set (seed App. I) on the GE-2000.

  Until its device link is configured every valid command ends `ERROR NO LINK TO GE-2000`.
  """
  @behaviour Vws.Partition

  @impl true
  def device, do: "GE-2000"

  @impl true
  def parse(text), do: Vws.Commands.parse(:monarch, text)

  @impl true
  def execute(_command, _ctx), do: {:error, "NO LINK TO GE-2000"}
end
