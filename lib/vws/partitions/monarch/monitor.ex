defmodule Vws.Partitions.Monarch.Monitor do
  @moduledoc """
  Keeps MONARCH's `MONARCH` device status (location 8, `ACTIVE`/`IDLE`) current: every
  `interval` ms it reads the GE-2000's status report over the DNC link
  (`Vws.Partitions.Monarch.refresh_status/3`).

  The seed's MONARCH reads the machine only for a STATUS command; the workstation controller
  follows a machining cycle by reading `S MONARCH` (its scripts' `WAIT MONARCH IDLE`), so the
  CEC reads the machine by itself, as VWS_STATUS reads DAQ #1 (decision). The reads share the
  half-duplex line with MONARCH's commands: the link serves one request at a time, so a read
  waits for a download in progress and never cuts into it. When the link is down nothing is
  written, and the location's age tells a reader the reading is stale.

  It is also the link's owner: a program the operator sends from the machine unasked
  (auto-receive) is handed to `Vws.Partitions.Monarch.received_program/4` with the `:store`
  function (default `Vws.Partitions.Monarch.store_from_machine/3`), and a program the operator
  asks for from the machine's panel (an `R` command) is answered by
  `Vws.Partitions.Monarch.RemoteRequest`.

  Started by `Vws.CEC.Workstation.device_links/3` with the GE-2000's link. Options: `:workstation`,
  `:link`, `:interval` (1 000 ms; `nil`: no status reads, the monitor only owns the link, so that
  programs from the machine are still kept), `:check` (`:lrc`), `:store`.

      iex> {:ok, pid} = Vws.Partitions.Monarch.Monitor.start_link(workstation: "none", link: :nowhere, interval: 60_000)
      iex> is_pid(pid)
      true
  """
  require Logger

  alias Vws.Partitions.{Monarch, StatusMonitor}

  @doc false
  def child_spec(opts), do: StatusMonitor.child_spec(__MODULE__, opts)

  @doc "Starts the MONARCH reader (a `Vws.Partitions.StatusMonitor`): its first read at once."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    options = Keyword.take(opts, [:check])
    store = Keyword.get(opts, :store, &Monarch.store_from_machine/3)

    StatusMonitor.start_link(opts, fn ws, link ->
      [
        # the read waits for the line while a transfer holds it; the monitor meanwhile takes that
        # transfer's progress (and a drip feed's ACTIVE, see machine_runs/2) as it comes
        read: fn -> Monarch.refresh_status(ws, link, options) end,
        failed: &"MONARCH cannot read the GE-2000's status: #{&1}",
        recovered: "MONARCH: the GE-2000's status reads again",
        # the link process this monitor owns (a restarted link is owned again)
        ext: %{link: link, owner: nil},
        tick: &own_link/1,
        handle: fn message, ext ->
          dnc(message, ws, store)
          ext
        end
      ]
    end)
  end

  # Programs the operator sends from the machine, unasked (auto-receive): handed to MONARCH.
  defp dnc({:dnc, _link, {:received, %{operation: :part_program} = command, blocks}}, ws, store) do
    name = String.trim(command.text)
    text = IO.iodata_to_binary(blocks)

    case Monarch.received_program(ws, name, text, store, length(blocks)) do
      :ok -> :ok
      {:error, reason} -> Logger.warning("MONARCH: program #{name} from the machine: #{reason}")
    end
  end

  # The operator asks for a program from the machine's panel (an R command): answered at once,
  # within the link's answer_timeout (Vws.Partitions.Monarch.RemoteRequest).
  defp dnc({:dnc, link, {:request, ref, %{operation: :part_program} = command, _}}, ws, _store) do
    Vws.Partitions.Monarch.RemoteRequest.answer(ws, link, ref, command)
    :ok
  end

  # A transfer's progress, told by the link: the workstation's event :dnc_progress
  # ({:vws_event, ws, :dnc_progress, payload}, payload as documented in Vws.Links.DNC).
  defp dnc({:dnc, _link, {:progress, payload}}, ws, _store) do
    machine_runs(ws, payload)

    with {:error, :no_such_event} <- Vws.CEC.Events.cause(ws, :dnc_progress, payload) do
      :ok = Vws.CEC.Events.create(ws, :dnc_progress)
      Vws.CEC.Events.cause(ws, :dnc_progress, payload)
    end
  rescue
    # the workstation's mailboxes are gone (it is stopping): nobody to tell
    ArgumentError -> :ok
  end

  defp dnc(_other, _ws, _store), do: :ok

  # A drip-fed program (operation E) runs from its first block until it ends, while the
  # half-duplex line carries it and no status report can be read: each block that reaches the
  # machine says so — MONARCH `ACTIVE`, the report naming the program it runs — so the WC, the
  # views and the table's interlock conditions see a running machine, not an old IDLE. Once the
  # feed has ended, the reports read again tell when the program is done.
  defp machine_runs(ws, %{operation: :download_execute, ended: false} = payload) do
    alarm =
      case Vws.CEC.Mailbox.readings(ws) do
        %{monarch: {%{alarm: alarm}, _age}} -> alarm
        _ -> 0
      end

    number =
      case Regex.run(~r/^\d{6}/, to_string(payload.program)) do
        [number] -> number
        nil -> "000000"
      end

    # (a status report asked for before this is not written over it: Monarch.put_status/3)
    Monarch.put_status(ws, %{state: :active, program: number, alarm: alarm})
  end

  defp machine_runs(_ws, _payload), do: :ok

  # The monitor is the link's owner: it is told what the machine sends of its own accord.
  defp own_link(s) do
    case GenServer.whereis(s.link) do
      pid when is_pid(pid) and pid == s.owner ->
        s

      pid when is_pid(pid) ->
        if Vws.Links.DNC.set_owner(pid, self()) == :ok, do: %{s | owner: pid}, else: s

      _ ->
        s
    end
  catch
    :exit, _ -> s
  end
end
