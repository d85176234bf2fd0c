defmodule Vws.Test.SafetyFloor do
  @moduledoc """
  The whole simulated shop floor (`Vws.Sim.Floor`: plant, DAQ #1, DAQ #2 with the hydraulic
  controller, GE-2000, VAL II, material handling) and a workstation wired to it, tuned to run fast: the plant at time scale 1000, the
  robot's motions a thousand times faster, short DNC/DDCMP/HPIB timers and short interlock
  timeouts. For the interlock rule tests, the stateful safety test and `bench/safety_soak.exs`,
  so it uses no ExUnit: `start/1` and `stop/1` are the caller's to pair.

  Commands go to the partitions the way SUN_COMM hands them over after parsing a WC string
  (`Vws.CEC.Mailbox.dispatch/4` and the partition's event).
  """

  alias Vws.CEC.Mailbox
  alias Vws.Sim.{Floor, Plant}

  @partitions [:robot, :monarch, :gripper, :fixture, :vacuum, :hydraulic]
  @program "%\nO100\nN10 M30\n%\n"

  # Timers. `:fast` (the stateful test, the soak): everything short, so that a sequence takes
  # tens of milliseconds; on a loaded machine more commands end in a timeout, which the safety
  # properties allow. `:steady` (the rule tests, the default): long enough that a loaded
  # machine does not turn an expected DONE into an error — DAQ #1 answers within a second
  # (a loaded suite has delayed its answers by 300 ms and more), a
  # reading is stale after two, and an interlock waits up to 1.5 s for a fresh one.
  @timing %{
    fast: %{
      dnc: [reply_timeout: 50, wack_delay: 10, backoff_min: 5, backoff_max: 50],
      ddcmp: [rep_timeout: 100, start_timeout: 50, backoff: {5, 50}],
      cycle_ms: 60,
      start_timeout: 150,
      device_ms: 200,
      val_ms: 500,
      hpib: [timeout: 60, connect_timeout: 200],
      vws_status: [poll_ms: 10, timeout_ms: 60, stale_after_ms: 150],
      interlock: [timeout: 60, retry_ms: 15, machine_stale_ms: 200, sensor_timeout_ms: 100]
    },
    steady: %{
      dnc: [reply_timeout: 500, wack_delay: 20, backoff_min: 5, backoff_max: 50],
      ddcmp: [rep_timeout: 300, start_timeout: 100, backoff: {5, 50}],
      cycle_ms: 1_000,
      start_timeout: 2_000,
      device_ms: 3_000,
      val_ms: 5_000,
      hpib: [timeout: 1_000, connect_timeout: 1_000],
      vws_status: [poll_ms: 10, timeout_ms: 1_000, stale_after_ms: 2_000],
      interlock: [timeout: 150, retry_ms: 30, machine_stale_ms: 600, sensor_timeout_ms: 1_500]
    }
  }

  @doc "The command partitions."
  def partitions, do: @partitions

  @doc """
  Starts a floor and its workstation. Options: `:timing` (`:steady`, the default, or `:fast`),
  `:interlock` (merged over the partitions' interlock options), `:cycle_ms` (the GE-2000's
  cycle), `:plant` (more plant options, e.g. `config:`), `:seed`. Returns
  `%{ws, floor, plant, daq, ge2000, robot, mhs, interlock}`.
  """
  def start(opts \\ []) do
    ws = "safety-#{System.unique_integer([:positive])}"
    # a library with a version of the selected program, for DOWNLOAD_GE(…/v) and COMPARE_GE
    library = Path.join(System.tmp_dir!(), "vws-#{ws}-library")
    {:ok, _} = Vws.CEC.Library.store({:dir, library}, "000100.PRO", @program)
    t = Map.fetch!(@timing, Keyword.get(opts, :timing, :steady))
    interlock = Keyword.merge(t.interlock, Keyword.get(opts, :interlock, []))

    {:ok, floor} =
      Floor.start_link(
        workstation: ws,
        time_scale: 1000,
        seed: Keyword.get(opts, :seed, 1),
        plant: Keyword.get(opts, :plant, []),
        ge2000: [
          link: t.dnc,
          cycle_time: Keyword.get(opts, :cycle_ms, t.cycle_ms),
          programs: %{"000100.PRO" => @program}
        ],
        robot: [ddcmp: t.ddcmp],
        hydraulic: {Vws.Peers.HydraulicController, [hpib: t.hpib]},
        mhs: [timeout: interlock[:timeout], retry_ms: interlock[:retry_ms], poll_ms: 2]
      )

    Process.unlink(floor)
    :ok = Vws.Peers.HydraulicController.await_ready(Floor.hydraulic_controller(ws), 5_000)
    devices = Floor.devices(ws)

    {:ok, _} =
      Vws.CEC.Workstation.start(
        id: ws,
        wc: nil,
        library: library,
        devices: [
          daq1: [
            endpoint: devices[:daq1],
            pulse_ms: 10,
            vws_status: t.vws_status,
            hpib: t.hpib
          ],
          ge2000: [endpoint: devices[:ge2000], status_interval: 20] ++ t.dnc,
          robot: [endpoint: devices[:robot], ddcmp: t.ddcmp],
          hydraulic: [endpoint: devices[:hydraulic], status_interval: 50, hpib: t.hpib]
        ],
        partitions: [
          robot: [
            options: [
              command_timeout: t.val_ms,
              motion_timeout: 2 * t.val_ms,
              program_timeout: 6 * t.val_ms,
              interlock: interlock
            ]
          ],
          monarch: [
            options: [
              start_timeout: t.start_timeout,
              poll_interval: 5,
              request_timeout: 2 * t.val_ms,
              interlock: interlock
            ]
          ],
          fixture: [options: [timeout_ms: t.device_ms, interlock: interlock]],
          gripper: [options: [timeout_ms: t.device_ms]],
          vacuum: [options: [timeout_ms: t.device_ms]],
          hydraulic: [options: [poll_ms: 5, timeout_ms: 4 * t.val_ms]]
        ]
      )

    f = %{
      ws: ws,
      floor: floor,
      plant: Floor.plant(ws),
      daq: Floor.daq1(ws),
      ge2000: Floor.ge2000(ws),
      robot: Floor.robot(ws),
      mhs: Floor.mhs(ws),
      interlock: interlock,
      library: library
    }

    ready =
      wait_until(
        fn ->
          match?({:ok, _}, Vws.Partitions.VwsStatus.readings(ws)) and
            match?({"IDLE", _}, Mailbox.get_device(ws, 8)) and
            Vws.Links.VAL.ready?(Vws.CEC.Workstation.whereis(ws, :val))
        end,
        5_000
      )

    unless ready, do: raise("the safety floor of #{ws} did not come up")
    :ok = Plant.set_part(f.plant, :vise, true)
    # an NC file for DOWNLOAD_GE and DRIP_FEED: a drip-fed run lasts a few hundred ms
    :ok =
      Mailbox.put_nc_file(
        ws,
        ["%", "O100"] ++ for(i <- 1..60, do: "N#{i} G01 X#{i}") ++ ["M30", "%"]
      )

    # a program ready for the cycle start
    :done = command(f, :monarch, "PROGRAM_SELECT(000100)")
    f
  end

  @doc "Stops the workstation and the floor."
  def stop(f) do
    _ = Vws.CEC.Workstation.stop(f.ws)
    if Process.alive?(f.floor), do: Supervisor.stop(f.floor, :shutdown, 5_000)
    File.rm_rf(f.library)
    :ok
  catch
    :exit, _ -> :ok
  end

  @doc """
  Hands `text` to `partition` as its next command and returns its number, or `{:busy, n}` while
  the partition's previous command `n` is still executing.
  """
  def dispatch(f, partition, text) do
    {last, _} = Mailbox.cmd_in(f.ws, partition)
    number = rem((last || 0) + 1, 10_000)

    case Vws.CEC.Partition.dispatch(f.ws, partition, number, text) do
      :ok ->
        number

      {:busy, n} ->
        {:busy, n}
    end
  end

  @doc """
  Waits until `partition` has no command in flight: `{:ok, {number, status}}`, or
  `{:executing, number}` when `timeout` ms passed first.
  """
  def await_idle(f, partition, timeout \\ 15_000) do
    # the command leaves flight a moment before its status is written
    idle? = fn ->
      Mailbox.in_flight(f.ws, partition) == nil and
        elem(Mailbox.command_status(f.ws, partition), 1) != :executing
    end

    if wait_until(idle?, timeout),
      do: {:ok, Mailbox.command_status(f.ws, partition)},
      else: {:executing, Mailbox.in_flight(f.ws, partition)}
  end

  @doc "Runs one command to its end: `:done` or `{:error, reason}` (raises if it never ends)."
  def command(f, partition, text, timeout \\ 15_000) do
    {:ok, _} = await_idle(f, partition, timeout)
    number = dispatch(f, partition, text)

    case await_idle(f, partition, timeout) do
      {:ok, {^number, status}} -> status
      other -> raise "#{partition} #{number} #{text}: #{inspect(other)}"
    end
  end

  @doc "The collisions the plant recorded."
  def collisions(f), do: Plant.collisions(f.plant)

  @doc "True as soon as `fun.()` is truthy; false when `timeout` ms pass first."
  def wait_until(fun, timeout), do: Vws.Test.Eventually.eventually(fun, timeout, 2)
end
