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
  use GenServer
  require Logger

  alias Vws.CEC.Mailbox
  alias Vws.Partitions.Hydraulic

  @doc false
  def child_spec(opts) do
    %{id: Keyword.get(opts, :id, __MODULE__), start: {__MODULE__, :start_link, [opts]}}
  end

  @doc "Starts the monitor; its first reading is taken at once."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts), do: GenServer.start_link(__MODULE__, opts)

  @impl true
  def init(opts) do
    s = %{
      workstation: Keyword.fetch!(opts, :workstation),
      link: Keyword.fetch!(opts, :link),
      interval: Keyword.get(opts, :interval, 1_000),
      timeout: Keyword.get(opts, :timeout, 1_000),
      failing: nil
    }

    if Mailbox.exists?(s.workstation),
      do: Mailbox.put_device(s.workstation, 10, "NO DATA (HYDRAULIC CONTROLLER NOT READ YET)")

    send(self(), :read)
    {:ok, s}
  end

  @impl true
  def handle_info(:read, s) do
    result =
      if Mailbox.exists?(s.workstation),
        do: Hydraulic.refresh_pallet(s.workstation, s.link, s.timeout),
        else: {:error, "NO MAILBOXES"}

    Process.send_after(self(), :read, s.interval)

    case result do
      {:ok, _pallet} ->
        if s.failing, do: Logger.info("HYDRAULIC: the hydraulic controller answers again")
        {:noreply, %{s | failing: nil}}

      {:error, why} ->
        # said once per outage, not once a second
        if s.failing != why, do: Logger.info("HYDRAULIC cannot read the pallet: #{why}")
        {:noreply, %{s | failing: why}}
    end
  end
end
