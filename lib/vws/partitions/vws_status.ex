defmodule Vws.Partitions.VwsStatus do
  @moduledoc """
  VWS_STATUS (seed §2.3.6): the partition that keeps the device-status mailbox locations 1–14.

  With no data-acquisition unit configured it says so truthfully in every location it is
  responsible for — `NO DATA (NO LINK TO DAQ #1)` — instead of leaving old or invented values; the
  locations that belong to other devices (MONARCH and TLI_TABLE to the GE-2000, WHERE_ROBOT to the
  VAL II, PALLET to the hydraulic controller) say which link they are waiting for until the
  partition of that device writes them.
  """
  use GenServer

  alias Vws.Mailbox

  @daq_locations [1, 2, 3, 4, 5, 7, 11]
  @other_locations [{6, "GE-2000"}, {8, "GE-2000"}, {9, "VAL II"}, {10, "HYDRAULIC CONTROLLER"}]

  @doc false
  def child_spec(opts), do: %{id: :vws_status, start: {__MODULE__, :start_link, [opts]}}

  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)
    GenServer.start_link(__MODULE__, opts, name: Vws.Partition.via(ws, :vws_status))
  end

  @impl true
  def init(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    for loc <- @daq_locations, Mailbox.get_device(ws, loc) |> elem(0) == nil do
      Mailbox.put_device(ws, loc, "NO DATA (NO LINK TO DAQ #1)")
    end

    for {loc, device} <- @other_locations, Mailbox.get_device(ws, loc) |> elem(0) == nil do
      Mailbox.put_device(ws, loc, "NO DATA (NO LINK TO #{device})")
    end

    {:ok, %{workstation: ws, daq: Keyword.get(opts, :daq)}}
  end
end
