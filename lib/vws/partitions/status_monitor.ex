defmodule Vws.Partitions.StatusMonitor do
  @moduledoc """
  A device-status reader: every `interval` ms it reads one device of a workstation over its link
  and lets the read write the device's mailbox location, so the workstation controller's `S
  <device>` is current without a command (as VWS_STATUS reads DAQ #1). The PALLET reader
  (`Vws.Partitions.Hydraulic.Monitor`) and the MONARCH reader (`Vws.Partitions.Monarch.Monitor`)
  are this process with their read.

  The read runs in a process of its own: one at a time, the next due `interval` ms after the end
  of the one before, and meanwhile the monitor takes its other messages (the GE-2000 link's
  transfer progress). Its answer may come back after someone else wrote the location (the
  partition's own confirmation, a drip feed's ACTIVE): the reads write with
  `Vws.CEC.Mailbox.put_device_unless_newer/4`, so older news is never written over newer. A read
  that fails is said in the log once per outage, not once a second; the first read that succeeds
  again says so.

  Options: `:workstation`, `:link`, `:interval` (ms, default 1000; `nil`: no reads, only the
  `:tick`); the device's parts are what `parts.(workstation, link)` gives:

    * `:read` — `fn -> {:ok, term} | {:error, why}` (run only while the workstation has
      mailboxes; without them the read fails with `NO MAILBOXES`);
    * `:failed` — `fn why -> log line` for the first failure of an outage;
    * `:recovered` — the log line when it reads again;
    * `:init` — `fn -> any` run when the monitor starts (default nothing);
    * `:tick` — `fn ext -> ext` before every read, and every second without reads;
    * `:handle` — `fn message, ext -> ext` for every other message; `:ext` its first state.
  """
  use GenServer
  require Logger

  @doc "The child spec of a monitor `module` (id: `opts[:id]` or the module)."
  @spec child_spec(module, keyword) :: Supervisor.child_spec()
  def child_spec(module, opts),
    do: %{id: Keyword.get(opts, :id, module), start: {module, :start_link, [opts]}}

  @doc """
  Starts a monitor of a device, whose parts `parts.(workstation, link)` gives (see the
  moduledoc); its first read is taken at once.
  """
  @spec start_link(keyword, (term, term -> keyword)) :: GenServer.on_start()
  def start_link(opts, parts) do
    ws = Keyword.fetch!(opts, :workstation)

    GenServer.start_link(
      __MODULE__,
      [workstation: ws, interval: Keyword.get(opts, :interval, 1_000)] ++
        parts.(ws, Keyword.fetch!(opts, :link))
    )
  end

  @impl true
  def init(opts) do
    s = %{
      workstation: Keyword.fetch!(opts, :workstation),
      interval: Keyword.fetch!(opts, :interval),
      read: Keyword.fetch!(opts, :read),
      failed: Keyword.fetch!(opts, :failed),
      recovered: Keyword.fetch!(opts, :recovered),
      tick: Keyword.get(opts, :tick, & &1),
      handle: Keyword.get(opts, :handle, fn _message, ext -> ext end),
      ext: Keyword.get(opts, :ext),
      failing: false,
      # the process reading, while it waits or reads
      reading: nil
    }

    if init = Keyword.get(opts, :init), do: init.()
    send(self(), :read)
    {:ok, s}
  end

  @impl true
  def handle_info(:read, %{interval: nil} = s) do
    Process.send_after(self(), :read, 1_000)
    {:noreply, tick(s)}
  end

  def handle_info(:read, %{reading: pid} = s) when is_pid(pid), do: {:noreply, s}

  def handle_info(:read, s) do
    s = tick(s)
    monitor = self()
    %{workstation: ws, read: read} = s

    pid =
      spawn_link(fn ->
        result = if Vws.CEC.Mailbox.exists?(ws), do: read.(), else: {:error, "NO MAILBOXES"}
        send(monitor, {:read_done, self(), result})
      end)

    {:noreply, %{s | reading: pid}}
  end

  def handle_info({:read_done, pid, result}, %{reading: pid} = s) do
    Process.send_after(self(), :read, s.interval)
    s = %{s | reading: nil}

    case result do
      {:ok, _} ->
        if s.failing, do: Logger.info(s.recovered)
        {:noreply, %{s | failing: false}}

      {:error, why} ->
        # said once per outage, not once a second
        unless s.failing, do: Logger.info(s.failed.(why))
        {:noreply, %{s | failing: true}}
    end
  end

  def handle_info(message, s), do: {:noreply, %{s | ext: s.handle.(message, s.ext)}}

  defp tick(s), do: %{s | ext: s.tick.(s.ext)}
end
