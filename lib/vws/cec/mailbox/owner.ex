defmodule Vws.CEC.Mailbox.Owner do
  @moduledoc """
  Owns a workstation's mailbox table and does nothing else, so the table survives the crash of any
  partition, link or SUN_COMM (the seed's memory files outlived the programs that wrote them).

  The table is public: every process of the workstation reads and writes it directly through
  `Vws.CEC.Mailbox`. It is registered in `Vws.Registry` under `{workstation, :mailbox}`.
  """
  use GenServer

  @doc false
  def child_spec(opts) do
    %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}, type: :worker}
  end

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    ws = Keyword.fetch!(opts, :workstation)

    GenServer.start_link(__MODULE__, ws, name: Vws.Names.via(ws, :mailbox_owner))
  end

  @impl true
  def init(ws) do
    table =
      :ets.new(:vws_mailbox, [:set, :public, read_concurrency: true, write_concurrency: true])

    Vws.CEC.Mailbox.initialize(table)
    {:ok, _} = Registry.register(Vws.Registry, {ws, :mailbox}, table)
    # CREATE EVENT "OK_TO_PROCEED" belongs to VWS_CONTROL, before any partition exists
    Vws.CEC.Events.create(ws, :ok_to_proceed)
    {:ok, %{workstation: ws, table: table}}
  end

  # LOCK ... UNLOCK: a function run inside the owner, serialised with every other locked section.
  @impl true
  def handle_call({:locked, fun}, _from, state), do: {:reply, fun.(state.table), state}
end
