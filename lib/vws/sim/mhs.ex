defmodule Vws.Sim.MHS do
  @moduledoc """
  The material-handling system (seed §2.3.8): the roller tables that bring trays 1 and 2 to the
  workstation and take them away, as a simulator on the plant (`Vws.Sim.Plant.move_tray/3`).

  It moves a tray on request (`move/4`, `request/3`) or by a scenario given at start
  (`scenario: [{:wait, ms} | {:move, tray, :in | :out}]`), one move at a time, in order.

  ## The interlocks it obeys (rules 2a, 2b)

  In the AMRF the MHS was a system of its own. Here it keeps to the CEC's interlocks two ways:

    * **logically** — before a move it asks the CEC for the tray's work volume through the
      product's API for outside equipment, `Vws.CEC.Workstation.acquire_volume(ws, :trayN, :mhs,
      timeout)`, the same M1/M2 procedure the CEC's partitions use: refused while the robot holds the tray (`DISABLE_TRAYn`, or the arm is in
      its volume) with `INTERLOCK TRAY1 HELD BY ROBOT`. It holds that lease until the tray has
      stopped, so the robot cannot approach a moving tray (rule 2a), and gives it up after;
    * **physically** — the plant refuses to move a tray whose lock relay (a DAQ #1 relay closed
      by `DISABLE_TRAYn`) holds it: `TRAY 1 LOCKED`.

  A workstation that is not running (no mailboxes) cannot grant a lease: the MHS does not move
  (`NO ANSWER FROM THE CEC`). A tray that does not arrive in time keeps the lease (it may still
  be moving).

  ## Options

  `:workstation` (required), `:plant` (required), `:name`, `:scenario`, `:timeout` (ms a lease
  is tried for, default 10 000), `:retry_ms` (250), `:move_timeout` (ms a tray may take to
  arrive, default 60 000), `:poll_ms` (how often the tray is looked at while it moves, 5).

      iex> {:ok, plant} = Vws.Sim.Plant.start_link(time_scale: 1000)
      iex> {:ok, mhs} = Vws.Sim.MHS.start_link(workstation: "mhs-doc-none", plant: plant)
      iex> Vws.Sim.MHS.move(mhs, 1, :out)
      {:error, "NO ANSWER FROM THE CEC"}
  """
  use GenServer
  require Logger

  alias Vws.Sim.Plant

  @type request :: {1 | 2, :in | :out}
  @type outcome :: %{tray: 1 | 2, direction: :in | :out, result: :ok | {:error, String.t()}}

  @doc false
  def child_spec(opts) do
    %{id: {__MODULE__, Keyword.get(opts, :name)}, start: {__MODULE__, :start_link, [opts]}}
  end

  @doc "Starts the MHS (options above)."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts) do
    {name, opts} = Keyword.pop(opts, :name)
    GenServer.start_link(__MODULE__, opts, if(name, do: [name: name], else: []))
  end

  @doc """
  Moves tray `tray` in or out and waits for the outcome: `:ok` once the tray has arrived, or
  `{:error, reason}` — `INTERLOCK TRAY1 HELD BY ROBOT`, `TRAY 1 LOCKED`, `TRAY 1 DID NOT ARRIVE`.
  """
  @spec move(GenServer.server(), 1 | 2, :in | :out, timeout) :: :ok | {:error, String.t()}
  def move(mhs, tray, direction, timeout \\ :infinity)
      when tray in [1, 2] and direction in [:in, :out],
      do: GenServer.call(mhs, {:move, {tray, direction}}, timeout)

  @doc "Asks for a move and returns at once; the outcome goes to `history/1`."
  @spec request(GenServer.server(), 1 | 2, :in | :out) :: :ok
  def request(mhs, tray, direction) when tray in [1, 2] and direction in [:in, :out],
    do: GenServer.cast(mhs, {:move, {tray, direction}})

  @doc "The outcomes of the moves so far, oldest first."
  @spec history(GenServer.server()) :: [outcome]
  def history(mhs), do: GenServer.call(mhs, :history)

  @doc "True while a move is under way or waiting."
  @spec busy?(GenServer.server()) :: boolean
  def busy?(mhs), do: GenServer.call(mhs, :busy?)

  ## Server

  @impl true
  def init(opts) do
    s = %{
      workstation: Keyword.fetch!(opts, :workstation),
      plant: Keyword.fetch!(opts, :plant),
      timeout: Keyword.get(opts, :timeout, 10_000),
      retry_ms: Keyword.get(opts, :retry_ms, 250),
      move_timeout: Keyword.get(opts, :move_timeout, 60_000),
      poll_ms: Keyword.get(opts, :poll_ms, 5),
      queue: :queue.new(),
      current: nil,
      history: []
    }

    s = Enum.reduce(Keyword.get(opts, :scenario, []), s, &enqueue(&2, &1, nil))
    {:ok, next(s)}
  end

  @impl true
  def handle_call({:move, req}, from, s),
    do: {:noreply, s |> enqueue({:move, req}, from) |> next()}

  def handle_call(:history, _from, s), do: {:reply, Enum.reverse(s.history), s}

  def handle_call(:busy?, _from, s),
    do: {:reply, s.current != nil or not :queue.is_empty(s.queue), s}

  @impl true
  def handle_cast({:move, req}, s), do: {:noreply, s |> enqueue({:move, req}, nil) |> next()}

  @impl true
  def handle_info({ref, result}, %{current: {ref, step, from}} = s) do
    Process.demonitor(ref, [:flush])

    s =
      case step do
        {:move, {tray, direction}} ->
          if from, do: GenServer.reply(from, result)
          if result != :ok, do: Logger.info("MHS: tray #{tray} #{direction}: #{inspect(result)}")
          %{s | history: [%{tray: tray, direction: direction, result: result} | s.history]}

        {:wait, _ms} ->
          s
      end

    {:noreply, next(%{s | current: nil})}
  end

  def handle_info({:DOWN, ref, :process, _pid, reason}, %{current: {ref, step, from}} = s) do
    result = {:error, "MHS FAILED #{inspect(reason)}"}
    if from, do: GenServer.reply(from, result)

    s =
      case step do
        {:move, {tray, direction}} ->
          %{s | history: [%{tray: tray, direction: direction, result: result} | s.history]}

        _ ->
          s
      end

    {:noreply, next(%{s | current: nil})}
  end

  def handle_info(_msg, s), do: {:noreply, s}

  defp enqueue(s, {:move, {tray, dir}} = step, from) when tray in [1, 2] and dir in [:in, :out],
    do: %{s | queue: :queue.in({step, from}, s.queue)}

  defp enqueue(s, {:move, tray, dir}, from), do: enqueue(s, {:move, {tray, dir}}, from)

  defp enqueue(s, {:wait, ms} = step, from) when is_integer(ms) and ms >= 0,
    do: %{s | queue: :queue.in({step, from}, s.queue)}

  # One step at a time, in a task of its own, so history/1 and busy?/1 answer meanwhile.
  defp next(%{current: nil} = s) do
    case :queue.out(s.queue) do
      {{:value, {step, from}}, queue} ->
        config = Map.take(s, [:workstation, :plant, :timeout, :retry_ms, :move_timeout, :poll_ms])
        %Task{ref: ref} = Task.async(fn -> run(step, config) end)
        %{s | queue: queue, current: {ref, step, from}}

      {:empty, _} ->
        s
    end
  end

  defp next(s), do: s

  defp run({:wait, ms}, _c), do: Process.sleep(ms)

  defp run({:move, {tray, direction}}, c) do
    volume = if tray == 1, do: :tray1, else: :tray2

    with :ok <- lease(c, volume) do
      case Plant.move_tray(c.plant, tray, direction) do
        :ok ->
          case arrive(c, tray, System.monotonic_time(:millisecond) + c.move_timeout) do
            :ok ->
              Vws.CEC.Workstation.release_volume(c.workstation, volume, :mhs)
              :ok

            # the tray may still be moving: the lease stays
            error ->
              error
          end

        {:error, :locked} ->
          Vws.CEC.Workstation.release_volume(c.workstation, volume, :mhs)
          {:error, "TRAY #{tray} LOCKED"}
      end
    end
  end

  defp lease(c, volume),
    do:
      Vws.CEC.Workstation.acquire_volume(c.workstation, volume, :mhs, c.timeout,
        retry_ms: c.retry_ms
      )

  # The lease is held until the tray has stopped: the robot must not meet a moving tray.
  defp arrive(c, tray, deadline) do
    cond do
      not Plant.snapshot(c.plant).trays[tray].moving ->
        :ok

      System.monotonic_time(:millisecond) > deadline ->
        {:error, "TRAY #{tray} DID NOT ARRIVE"}

      true ->
        Process.sleep(c.poll_ms)
        arrive(c, tray, deadline)
    end
  end
end
