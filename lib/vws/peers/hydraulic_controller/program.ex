defmodule Vws.Peers.HydraulicController.Program do
  @moduledoc false
  # The HP-9836 program (seed §5.1) behind the `Vws.Peers.HydraulicController` facade: its three
  # initialisation routines, in order, then the task manager `Options` for each CEC connection.
  #
  #   init_cec_link ─▶ init_daq2_link ─▶ depressurise ─▶ options (accepting, :ready)
  #                      └──── in a worker process ────┘
  #
  # The program keeps the command status (`STATUS?`), runs each CLAMP_PALLET / RELEASE_PALLET
  # in a linked worker process (so the status is answered while a sequence runs), and owns the
  # acceptor and the connection handlers (`Vws.Peers.HydraulicController.Options`), all linked to it:
  # none of their failures stops the program — a program restart depressurises the pallet.
  use GenServer
  require Logger

  alias Vws.Peers.HydraulicController.{CecPort, Options, Pallet}
  alias Vws.Links.Transport

  def start_link(opts) do
    GenServer.start_link(__MODULE__, opts, name: Keyword.fetch!(opts, :registered_as))
  end

  ## Server

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    name = Keyword.fetch!(opts, :name)
    Logger.metadata(hydraulic_controller: name)

    s = %{
      name: name,
      cec_port: Keyword.fetch!(opts, :cec_port),
      allow: Keyword.get(opts, :allow, :loopback),
      pallet: Keyword.fetch!(opts, :pallet),
      connect_timeout_ms: Keyword.fetch!(opts, :connect_timeout_ms),
      listener: nil,
      acceptor: nil,
      phase: :initialising,
      status: :executing,
      depressurised: false,
      worker: nil,
      connections: MapSet.new(),
      counts: %{connections: 0, commands: 0, refused_busy: 0, sequences: 0},
      init_result: nil,
      waiting_ready: []
    }

    {:ok, s, {:continue, :init_cec_link}}
  end

  @impl true
  def handle_continue(:init_cec_link, s) do
    case init_cec_link(s) do
      {:ok, s} ->
        # routines 2 and 3 talk to DAQ #2 and may take seconds: in a worker, so the program
        # answers (endpoint, info) meanwhile
        pallet = s.pallet
        timeout = s.connect_timeout_ms

        worker =
          spawn_link(fn ->
            result = with :ok <- init_daq2_link(pallet, timeout), do: depressurise(pallet)

            exit({:shutdown, {:sequence, :init, result}})
          end)

        {:noreply, %{s | worker: {worker, :init}}}

      {:error, reason} ->
        {:stop, {:no_cec_link, reason}, s}
    end
  end

  @impl true
  def handle_call(:endpoint, _from, s),
    do: {:reply, to_string(Transport.listener_endpoint(s.listener)), s}

  def handle_call(:status, _from, s), do: {:reply, s.status, s}

  def handle_call(:pallet, _from, s), do: {:reply, s.pallet, s}

  def handle_call(:info, _from, s) do
    info =
      Map.merge(s.counts, %{
        phase: s.phase,
        status: s.status,
        depressurised: s.depressurised,
        running: s.worker && elem(s.worker, 1),
        open_connections: MapSet.size(s.connections),
        init_result: s.init_result,
        endpoint: s.listener && to_string(Transport.listener_endpoint(s.listener))
      })

    {:reply, info, s}
  end

  def handle_call(:await_ready, from, %{phase: :initialising} = s),
    do: {:noreply, %{s | waiting_ready: [from | s.waiting_ready]}}

  def handle_call(:await_ready, _from, s), do: {:reply, :ok, s}

  def handle_call({:run, command}, _from, %{worker: {_pid, running}} = s) do
    Logger.warning(
      "hydraulic controller: #{command_text(command)} not run, #{command_text(running)} is executing"
    )

    {:reply, {:error, :busy}, update_in(s.counts.refused_busy, &(&1 + 1))}
  end

  def handle_call({:run, command}, _from, s) when command in [:clamp_pallet, :release_pallet] do
    {:reply, :ok, start_sequence(command, s)}
  end

  @impl true
  def handle_info({:accepted, conn}, s) do
    handler = Options.start_link(conn, self())
    :ok = Transport.controlling_process(conn, handler)
    send(handler, :go)

    {:noreply,
     %{s | connections: MapSet.put(s.connections, handler)}
     |> then(&update_in(&1.counts.connections, fn n -> n + 1 end))}
  end

  def handle_info({:depressurised, pid}, %{worker: {pid, _}} = s),
    do: {:noreply, %{s | depressurised: true}}

  def handle_info({:EXIT, pid, reason}, %{worker: {pid, what}} = s) do
    result =
      case reason do
        {:shutdown, {:sequence, ^what, result}} -> result
        other -> {:error, "CRASHED #{other |> inspect(limit: 5) |> String.upcase()}"}
      end

    {:noreply, sequence_done(what, result, %{s | worker: nil})}
  end

  def handle_info({:EXIT, pid, reason}, %{acceptor: pid} = s),
    do: {:stop, {:acceptor_down, reason}, s}

  def handle_info({:EXIT, pid, reason}, s) do
    if MapSet.member?(s.connections, pid) do
      unless reason in [:normal, :shutdown],
        do:
          Logger.warning(
            "hydraulic controller: a CEC connection handler ended #{inspect(reason)}"
          )

      {:noreply, %{s | connections: MapSet.delete(s.connections, pid)}}
    else
      # our supervisor is going down
      {:stop, reason, s}
    end
  end

  def handle_info(msg, s) do
    Logger.debug("hydraulic controller: unexpected message #{inspect(msg, limit: 10)}")
    {:noreply, s}
  end

  ## The three initialisation routines (seed §5.1), in order

  # 1. The HPIB link with the CEC: the controller is a device on the CEC's bus, reached at its
  #    own endpoint, bound by the CEC port process (so it stays the same when the program
  #    restarts). Connections wait there until the program is ready (`options`).
  defp init_cec_link(s) do
    listener = CecPort.listener(s.cec_port)

    Logger.info(
      "hydraulic controller: HPIB link to the CEC on #{Transport.listener_endpoint(listener)}"
    )

    {:ok, %{s | listener: listener}}
  catch
    :exit, reason -> {:error, reason}
  end

  # 2. The HPIB link with DAQ #2: the controller is the controller-in-charge of its own bus; its
  #    `Vws.Links.HPIB` device (started before the program) connects by itself; this waits for it
  #    and identifies the instrument.
  defp init_daq2_link(pallet, timeout) do
    case Vws.Links.HPIB.await_connected(pallet.device, timeout) do
      :ok -> Pallet.identify(pallet)
      :timeout -> {:error, Pallet.hpib_reason(%Vws.Links.HPIB.Error{reason: :not_connected})}
    end
  end

  # 3. Depressurise the valves so the swing clamps are fully released before any command.
  defp depressurise(pallet), do: Pallet.depressurise(pallet)

  # The task manager: accept the CEC's connections; each gets an `Options` loop.
  defp options(s) do
    # only the CEC (the allow-list) reaches the program; anyone else is closed by the acceptor
    acceptor = Transport.start_acceptor(s.listener, self(), :accepted, allow: s.allow)
    %{s | acceptor: acceptor, phase: :ready}
  end

  ## Sequences

  defp start_sequence(command, s) do
    pallet = s.pallet
    # the seed's depressurise precedes any clamping: if it could not be done at start-up, it is
    # done now, before the clamps are asked to act
    first = if command == :clamp_pallet and not s.depressurised, do: [:depressurise], else: []

    program = self()

    worker =
      spawn_link(fn ->
        result =
          Enum.reduce_while(first ++ [command], :done, fn step, :done ->
            case apply(Pallet, step, [pallet]) do
              :done ->
                if step == :depressurise, do: send(program, {:depressurised, self()})
                {:cont, :done}

              error ->
                {:halt, error}
            end
          end)

        exit({:shutdown, {:sequence, command, result}})
      end)

    Logger.info("hydraulic controller: #{command_text(command)}")

    %{
      s
      | worker: {worker, command},
        status: :executing,
        counts: %{s.counts | commands: s.counts.commands + 1}
    }
  end

  defp sequence_done(:init, result, s) do
    case result do
      :done ->
        Logger.info("hydraulic controller: depressurised, ready for commands")

      {:error, why} ->
        Logger.warning(
          "hydraulic controller: could not depressurise at start-up (#{why}); " <>
            "CLAMP_PALLET will depressurise first"
        )
    end

    for from <- s.waiting_ready, do: GenServer.reply(from, :ok)

    %{
      s
      | status: init_status(result),
        depressurised: result == :done,
        init_result: result,
        waiting_ready: []
    }
    |> options()
  end

  defp sequence_done(command, result, s) do
    Logger.info("hydraulic controller: #{command_text(command)} #{inspect(result)}")

    # a completed release leaves the clamps confirmed released, as depressurising does
    depressurised = s.depressurised or {command, result} == {:release_pallet, :done}

    %{
      s
      | status: result,
        depressurised: depressurised,
        counts: %{s.counts | sequences: s.counts.sequences + 1}
    }
  end

  defp init_status(:done), do: :done
  defp init_status({:error, why}), do: {:error, "NOT DEPRESSURISED AT START-UP: " <> why}

  defp command_text(:clamp_pallet), do: "CLAMP_PALLET"
  defp command_text(:release_pallet), do: "RELEASE_PALLET"
  defp command_text(:init), do: "the start-up routines"
end
