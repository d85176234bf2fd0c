defmodule Vws.Partitions.Hydraulic do
  @moduledoc """
  HYDRAULIC (seed §2.2 item 8, App. I F): the partition that runs the hydraulic command set on
  the hydraulic controller (`Vws.Peers.HydraulicController`), a device on the CEC's HPIB (`ctx.link`
  is its `Vws.Links.HPIB` device `{bus, address}`).

  `CLAMP_PALLET` and `RELEASE_PALLET` go to the controller as they are; then HYDRAULIC asks
  `STATUS?` every `:poll_ms` until the answer is not `EXECUTING`:

    * `DONE` — and `PALLET?` confirms it (clamped after CLAMP_PALLET, not clamped after
      RELEASE_PALLET), so a controller that restarted during the command cannot pass for one
      that finished it: the command ends `DONE`, location 10 is updated at once. Else
      `ERROR PALLET NOT CLAMPED AFTER CLAMP_PALLET (X=1 Y=1 F1=5000 N F2=0 N)`.
    * `ERROR <reason>` — the command ends with the controller's reason, what it measured:
      `ERROR CLAMP 2 FORCE 1200 N BELOW 4000 N`, `ERROR PALLET NOT AGAINST X STOP`,
      `ERROR DAQ #2 NOT ANSWERING (NO ANSWER IN 500 MS)`.

  Before sending, it waits until the controller is not `EXECUTING` (a sequence a previous CEC
  run started), so a status it reads is always its own command's. A controller that does not
  answer ends the command `ERROR HYDRAULIC CONTROLLER NOT ANSWERING (NO ANSWER IN 1000 MS)` once
  nothing has been answered for `:silence_ms`; one that cannot be reached at all,
  `ERROR HYDRAULIC CONTROLLER NOT CONNECTED`; a command still `EXECUTING` after `:timeout_ms`,
  `ERROR HYDRAULIC CONTROLLER STILL EXECUTING AFTER n MS`.

  ## The PALLET status (location 10)

  `refresh_pallet/3` asks `PALLET?` and writes `PALLET CLAMPED` or `PALLET NOT CLAMPED` (seed
  App. I G); when the controller cannot read DAQ #2 (forces at the overload value),
  `NO DATA (HYDRAULIC CONTROLLER CANNOT READ THE PALLET SENSORS)`; when the controller does not
  answer, `NO DATA (HYDRAULIC CONTROLLER NOT ANSWERING)` (or `NOT CONNECTED`, `BAD ANSWER`) — an
  old reading is never left standing. `Vws.Partitions.Hydraulic.Monitor` calls it every second.

  Options (`ctx.options`): `:poll_ms` (100), `:timeout_ms` (60 000: a whole sequence),
  `:silence_ms` (3000), `:request_ms` (one HPIB request, 1000).
  """
  @behaviour Vws.CEC.Partition.CommandSet

  require Logger

  alias Vws.Links.HPIB
  alias Vws.CEC.Mailbox

  @device "HYDRAULIC CONTROLLER"
  @pallet_location 10
  @overload_at 1.0e37

  @defaults [poll_ms: 100, timeout_ms: 60_000, silence_ms: 3_000, request_ms: 1_000]

  @impl true
  def device, do: @device

  @impl true
  def parse(text), do: Vws.Codecs.Commands.parse(:hydraulic, text)

  @impl true
  def execute(command, ctx) when command in [:clamp_pallet, :release_pallet] do
    opts = Keyword.merge(@defaults, ctx.options)
    now = now()

    run = %{
      link: ctx.link,
      opts: opts,
      deadline: now + opts[:timeout_ms],
      last_answer: now,
      last_error: nil
    }

    with {:ok, run} <- await_not_executing(run, :before),
         :ok <- send_command(run, command),
         {:ok, _run} <- await_not_executing(%{run | last_answer: now()}, :after) do
      confirm(ctx.workstation, ctx.link, command, opts[:request_ms])
    end
  end

  # Asks STATUS? until it is not EXECUTING. Before the command any settled status will do; after
  # it, DONE is `:ok` and ERROR the command's error.
  defp await_not_executing(run, phase) do
    case HPIB.query(run.link, :status?, run.opts[:request_ms]) do
      {:ok, :executing} ->
        wait_more(%{run | last_answer: now()}, phase, :executing)

      {:ok, :done} ->
        {:ok, run}

      {:ok, {:error, _reason}} when phase == :before ->
        {:ok, run}

      {:ok, {:error, reason}} ->
        {:error, reason}

      {:error, %HPIB.Error{reason: :no_device}} ->
        {:error, "NO LINK TO #{@device}"}

      {:error, error} ->
        wait_more(%{run | last_error: error}, phase, :no_answer)
    end
  end

  defp wait_more(run, phase, why) do
    now = now()

    cond do
      why == :no_answer and now - run.last_answer >= run.opts[:silence_ms] ->
        {:error, hpib_reason(run.last_error)}

      now >= run.deadline and why == :executing ->
        {:error, "#{@device} STILL EXECUTING AFTER #{run.opts[:timeout_ms]} MS"}

      now >= run.deadline ->
        {:error, hpib_reason(run.last_error)}

      true ->
        Process.sleep(run.opts[:poll_ms])
        await_not_executing(run, phase)
    end
  end

  defp send_command(run, command) do
    case HPIB.write(run.link, command, run.opts[:request_ms]) do
      :ok -> :ok
      {:error, error} -> {:error, hpib_reason(error)}
    end
  end

  # Positive verification (seed §6): the pallet as the controller reads it after DONE — the
  # same verdict twice in a row (at most four readings), so that one reading damaged on a line
  # (a switch bit, a digit) decides nothing either way.
  defp confirm(ws, link, command, timeout), do: confirm(ws, link, command, timeout, 4, nil)

  defp confirm(ws, link, command, timeout, reads, previous) do
    read = refresh_pallet(ws, link, timeout)

    if reads > 1 and not same_verdict?(read, previous),
      do: confirm(ws, link, command, timeout, reads - 1, read),
      else: verdict(read, command)
  end

  defp same_verdict?({:ok, %{clamped: a}}, {:ok, %{clamped: b}}), do: a == b
  defp same_verdict?(_read, _previous), do: false

  defp verdict(read, command) do
    want = command == :clamp_pallet

    case read do
      {:ok, %{clamped: ^want}} ->
        :done

      {:ok, pallet} ->
        {:error,
         "PALLET #{if want, do: "NOT CLAMPED", else: "STILL CLAMPED"} AFTER " <>
           "#{command |> to_string() |> String.upcase()} (#{readings(pallet)})"}

      {:error, why} ->
        {:error, "#{command |> to_string() |> String.upcase()} DONE BUT PALLET NOT READ: #{why}"}
    end
  end

  @doc """
  Reads `PALLET?` from the controller at `link` and writes the `PALLET` status (location 10).
  Returns the decoded answer, or `{:error, why}` with the `NO DATA` reason it wrote.

  Nothing is written when location 10 was written since the read was asked for
  (`Mailbox.put_device_unless_newer/4`): the PALLET monitor's read, answered before a
  CLAMP_PALLET ended and handed back after HYDRAULIC's own confirmation wrote `PALLET CLAMPED`,
  would otherwise show `PALLET NOT CLAMPED` after `DONE` until the next read.
  """
  @spec refresh_pallet(Mailbox.workstation(), HPIB.device(), timeout) ::
          {:ok, Vws.Codecs.SCPI.pallet()} | {:error, String.t()}
  def refresh_pallet(ws, link, timeout \\ 1_000) do
    asked_at = System.monotonic_time(:millisecond)

    {text, result} =
      case HPIB.query(link, :pallet?, timeout) do
        {:ok, pallet} ->
          {pallet_text(pallet), {:ok, pallet}}

        {:error, error} ->
          why = hpib_reason(error)
          {"NO DATA (#{no_data_reason(error, why)})", {:error, why}}
      end

    with :ok <- Mailbox.put_device_unless_newer(ws, @pallet_location, text, asked_at),
         {:ok, pallet} <- result,
         do: Mailbox.put_readings(ws, :pallet, pallet)

    result
  end

  @doc """
  The `PALLET` status text of a `PALLET?` answer.

      iex> Vws.Partitions.Hydraulic.pallet_text(%{clamped: true, x: true, y: true, force1_n: 5000.0, force2_n: 4990.0})
      "PALLET CLAMPED"
      iex> Vws.Partitions.Hydraulic.pallet_text(%{clamped: false, x: false, y: false, force1_n: 9.9e37, force2_n: 9.9e37})
      "NO DATA (HYDRAULIC CONTROLLER CANNOT READ THE PALLET SENSORS)"
  """
  @spec pallet_text(Vws.Codecs.SCPI.pallet()) :: String.t()
  def pallet_text(%{clamped: true}), do: "PALLET CLAMPED"

  def pallet_text(%{force1_n: f1, force2_n: f2}) when f1 >= @overload_at or f2 >= @overload_at,
    do: "NO DATA (#{@device} CANNOT READ THE PALLET SENSORS)"

  def pallet_text(%{clamped: false}), do: "PALLET NOT CLAMPED"

  defp readings(p) do
    "X=#{bit(p.x)} Y=#{bit(p.y)} F1=#{force(p.force1_n)} F2=#{force(p.force2_n)}"
  end

  defp bit(true), do: "1"
  defp bit(false), do: "0"
  defp force(n) when n >= @overload_at, do: "OVERLOAD"
  defp force(n), do: Vws.Links.DAQ.DeviceStatus.newtons(n) <> " N"

  # the status text says what is wrong, the command error also how long it was waited for
  defp no_data_reason(%HPIB.Error{reason: :timeout}, _why), do: "#{@device} NOT ANSWERING"

  defp no_data_reason(%HPIB.Error{reason: :not_connected, detail: :timeout}, _why),
    do: "#{@device} NOT ANSWERING"

  defp no_data_reason(_error, why), do: why

  @doc "An HPIB error on the link to the controller, as a status reason."
  @spec hpib_reason(HPIB.Error.t() | nil) :: String.t()
  def hpib_reason(%HPIB.Error{} = error), do: HPIB.Error.status_reason(error, @device)
  def hpib_reason(nil), do: "#{@device} NOT ANSWERING"

  @doc """
  What a workstation needs to reach the hydraulic controller at `endpoint`: its `Vws.Links.HPIB`
  device and the PALLET monitor for the links supervisor, and HYDRAULIC's `link:`. Options:
  `:address` (the controller's primary address on the CEC's HPIB, default 8), `:hpib`
  (`Vws.Links.HPIB.start_link/1` options), `:status_interval` (ms between PALLET reads, default 1000;
  `nil` for no monitor), `:status_timeout` (ms one PALLET read may take, default 1000),
  `:hydraulic` (partition options, e.g. `options: [timeout_ms: …]`).
  """
  @spec wiring(Mailbox.workstation(), String.t() | Vws.Links.Endpoint.t(), keyword) ::
          %{links: [Supervisor.child_spec()], partitions: keyword}
  def wiring(ws, endpoint, opts \\ []) do
    address = Keyword.get(opts, :address, 8)
    link = {ws, address}

    hpib =
      HPIB.child_spec(
        [bus: ws, address: address, endpoint: endpoint, device: @device] ++
          Keyword.get(opts, :hpib, [])
      )

    monitor =
      case Keyword.get(opts, :status_interval, 1_000) do
        nil ->
          []

        ms ->
          [
            {__MODULE__.Monitor,
             workstation: ws,
             link: link,
             interval: ms,
             timeout: Keyword.get(opts, :status_timeout, 1_000)}
          ]
      end

    %{
      links: [hpib | monitor],
      partitions: [hydraulic: [link: link] ++ Keyword.get(opts, :hydraulic, [])]
    }
  end

  defp now, do: System.monotonic_time(:millisecond)
end
