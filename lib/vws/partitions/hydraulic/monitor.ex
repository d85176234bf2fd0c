defmodule Vws.Partitions.Hydraulic.Monitor do
  @moduledoc """
  Keeps the `PALLET` device status (location 10) current: every `interval` ms it asks the
  hydraulic controller `PALLET?` over the HPIB (`Vws.Partitions.Hydraulic.refresh_pallet/3`).

  The seed's CEC learns the pallet's state only from the hydraulic controller; the workstation
  controller reads `S PALLET` whenever it likes, so the CEC reads it by itself, as VWS_STATUS
  reads DAQ #1 (decision). A read that fails overwrites the location at once with
  `NO DATA (HYDRAULIC CONTROLLER NOT ANSWERING)` (or `NOT CONNECTED`): a stale reading is never
  shown as fresh. Before its first answer the location reads
  `NO DATA (HYDRAULIC CONTROLLER NOT READ YET)`.

  Started by `Vws.Partitions.Hydraulic.wiring/3` under the workstation's links supervisor.
  Options: `:workstation`, `:link` (the controller's `Vws.Links.HPIB` device), `:interval` (1000 ms),
  `:timeout` (one read, 1000 ms).

      iex> {:ok, pid} = Vws.Partitions.Hydraulic.Monitor.start_link(workstation: "none", link: {"none", 8}, interval: 60_000)
      iex> is_pid(pid)
      true
  """
  alias Vws.CEC.Mailbox
  alias Vws.Partitions.{Hydraulic, StatusMonitor}

  @doc false
  def child_spec(opts), do: StatusMonitor.child_spec(__MODULE__, opts)

  @doc "Starts the PALLET reader (a `Vws.Partitions.StatusMonitor`): its first read at once."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    timeout = Keyword.get(opts, :timeout, 1_000)

    StatusMonitor.start_link(opts, fn ws, link ->
      [
        init: fn ->
          if Mailbox.exists?(ws),
            do: Mailbox.put_device(ws, 10, "NO DATA (HYDRAULIC CONTROLLER NOT READ YET)")
        end,
        read: fn -> Hydraulic.refresh_pallet(ws, link, timeout) end,
        failed: &"HYDRAULIC cannot read the pallet: #{&1}",
        recovered: "HYDRAULIC: the hydraulic controller answers again"
      ]
    end)
  end
end
