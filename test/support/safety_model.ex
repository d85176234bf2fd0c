defmodule Vws.Test.SafetyModel do
  @moduledoc """
  The `:proper_statem` model of the safety test (`test/vws/safety_statem_test.exs`) and of
  `bench/safety_soak.exs`: random sequences of WC commands for every partition, moves of the
  material-handling system and injected faults, run against the real partitions and simulators
  (`Vws.Test.SafetyFloor`, a fresh floor per sequence).

  The commands cover every kind of every set (`texts/0`, checked against
  `Vws.Codecs.Commands.kinds/0`), ours included — `DRIP_FEED`, `DRIP_FEED(nnnnnn.PRO/v/Nk)`, `DOWNLOAD_GE(nnnnnn.PRO/v)`,
  `COMPARE_GE` — and the operator sends programs from the machine (`from_machine/1`) and asks
  for them from its panel (`remote_request/2`).

  Commands are handed to the partitions as SUN_COMM hands them over, without waiting for them
  to finish — so several partitions run at once and race for the work volumes; a partition whose
  previous command still runs is waited for first (SUN_COMM would answer `ERROR BUSY`).

  Postconditions, after every step and at the end of the sequence:

    * the plant's collision oracle records no conflict (`:part_dropped` — the gripper opened
      with nothing under the part — is not one of the seed's interlocks: the gripper has none);
    * every command ends `DONE` or `ERROR <reason>` with a reason;
    * none stays `EXECUTING`: each has ended within `@stuck_ms` of being waited for.

  The model keeps no prediction of what the CEC should answer — refusals and errors are fine;
  only safety and termination are checked.

      property =
        :proper.forall(Vws.Test.SafetyModel.commands(), fn cmds ->
          Vws.Test.SafetyModel.run(cmds) == :ok
        end)
  """

  alias Vws.Test.SafetyFloor
  alias Vws.Sim.{DAQ, GE2000, MHS, Plant, VAL2}

  @stuck_ms 15_000
  @ignored [:part_dropped]

  @robot [
    {6, "DO MOVE SAFE"},
    {4, "DO APPRO VISE/50"},
    {3, "DO MOVES VISE"},
    {3, "DO APPROS TRAY1/50"},
    {2, "DO MOVE TRAY1"},
    {2, "DO APPRO TRAY2/50"},
    {2, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"},
    {1, "DO MOVES MV1:TRANS(63.5,-300,0,90,-90,0)"},
    {1, "DO MOVE MV3:TRANS(0,-250,0,90,-90,0)"},
    {2, "DO DEPARTS 50"},
    {3, "DISABLE_TABLE"},
    {4, "RELEASE_TABLE"},
    {2, "DISABLE_TRAY1"},
    {3, "RELEASE_TRAY1"},
    {1, "DISABLE_TRAY2"},
    {2, "RELEASE_TRAY2"},
    {1, "EXECUTE DEBURR"},
    {1, "EXECUTE PARK"},
    {1, "WHERE"},
    {1, "SPEED 80"},
    {1, "DO MOVE NOWHERE"}
  ]
  @monarch [
    {3, "PROGRAM_SELECT(000100)"},
    {6, "CYCLE_START"},
    {5, "RELEASE_TABLE"},
    {1, "STATUS"},
    {1, "TABLE(1/3)"},
    {1, "UPLOAD_GE(000100.PRO)"},
    {1, "DOWNLOAD_GE"},
    {3, "DRIP_FEED"},
    {1, "DRIP_FEED(000100.PRO/1/N3)"},
    {1, "DOWNLOAD_GE(000100.PRO/1)"},
    {1, "DOWNLOAD_GE(000100.PRO)"},
    {1, "COMPARE_GE"},
    {1, "COMPARE_GE(000100.PRO)"},
    {1, "PROGRAM_DELETE(000100.PRO)"}
  ]
  # SUN_COMM carries these out on the WC link; handed to MONARCH they end ERROR in words
  @transfers [{1, "DOWNLOAD_HP"}, {1, "UPLOAD_SUN"}]
  @fixture [{4, "OPEN"}, {4, "CLOSE"}, {2, "DISABLE_TABLE"}, {3, "RELEASE_TABLE"}]
  @gripper [{2, "OPEN"}, {2, "CLOSE"}, {1, "ROTATE_90"}]
  @vacuum [{1, "ON"}, {1, "OFF"}]
  @hydraulic [{1, "CLAMP_PALLET"}, {1, "RELEASE_PALLET"}]

  @faults [
    {:plant, :broken_switch, [switch: :table_park]},
    {:plant, :sensor_open_circuit, [signal: :table_park]},
    {:plant, :broken_switch, [switch: :vise_fully_open]},
    {:plant, :sensor_open_circuit, [signal: :vise_force_n]},
    {:plant, :stuck_valve, [actuator: :vise_open_valve]},
    {:plant, :stuck_valve, [actuator: :vise_close_valve]},
    {:plant, :stuck_valve, [actuator: :tray1_lock]},
    {:plant, :weak_clamp, [where: :vise, force_n: 300]},
    :daq_mute,
    :daq_slow,
    :ge_silent,
    :ge_drop_replies,
    :val_fault,
    :val_restart,
    {:kill, :robot},
    {:kill, :monarch},
    {:kill, :fixture},
    {:kill, :vws_status}
  ]

  ## Generation

  @doc "The command-sequence generator (at most about `size` steps each)."
  def commands(size \\ 10), do: :proper_types.resize(size, :proper_statem.commands(__MODULE__))

  @doc false
  def initial_state, do: %{faults: 0, steps: 0}

  @doc false
  def command(_state) do
    :proper_types.frequency([
      {14, {:call, __MODULE__, :wc, [:robot, text(@robot)]}},
      {8, {:call, __MODULE__, :wc, [:monarch, text(@monarch ++ @transfers)]}},
      {7, {:call, __MODULE__, :wc, [:fixture, text(@fixture)]}},
      {2, {:call, __MODULE__, :wc, [:gripper, text(@gripper)]}},
      {1, {:call, __MODULE__, :wc, [:vacuum, text(@vacuum)]}},
      {1, {:call, __MODULE__, :wc, [:hydraulic, text(@hydraulic)]}},
      {1, {:call, __MODULE__, :wc, [partition(), "BOGUS"]}},
      {4,
       {:call, __MODULE__, :mhs, [:proper_types.oneof([1, 2]), :proper_types.oneof([:in, :out])]}},
      {1,
       {:call, __MODULE__, :from_machine, [:proper_types.oneof(["000100.PRO", "000200.PRO"])]}},
      {1,
       {:call, __MODULE__, :remote_request,
        [:proper_types.oneof([100, 200]), :proper_types.oneof([nil, 1, 2])]}},
      {3, {:call, __MODULE__, :fault, [:proper_types.oneof(@faults)]}},
      {2, {:call, __MODULE__, :heal, []}},
      {3, {:call, __MODULE__, :pause, [:proper_types.oneof([1, 5, 20, 40])]}},
      {1, {:call, __MODULE__, :settle, []}}
    ])
  end

  @doc """
  Every command text the model generates, by partition: the safety test checks that they cover
  every kind of every set (`Vws.Codecs.Commands.kinds/0`).
  """
  def texts do
    %{
      robot: @robot,
      monarch: @monarch ++ @transfers,
      fixture: @fixture,
      gripper: @gripper,
      vacuum: @vacuum,
      hydraulic: @hydraulic
    }
    |> Map.new(fn {p, weighted} -> {p, Enum.map(weighted, &elem(&1, 1))} end)
  end

  defp text(weighted), do: :proper_types.frequency(for {w, t} <- weighted, do: {w, t})
  defp partition, do: :proper_types.oneof(SafetyFloor.partitions())

  @doc false
  def precondition(_state, _call), do: true

  @doc false
  def next_state(state, _result, {:call, _, :fault, _}),
    do: %{state | faults: state.faults + 1, steps: state.steps + 1}

  def next_state(state, _result, _call), do: %{state | steps: state.steps + 1}

  @doc false
  def postcondition(_state, _call, result), do: result == :ok

  ## Running

  @doc """
  Runs one sequence on a fresh floor and checks the end: `:ok`, or `{:failed, report}` with the
  history, the collisions and the command statuses.
  """
  def run(cmds, opts \\ []) do
    f = SafetyFloor.start(Keyword.put_new(opts, :timing, :fast))
    Process.put(:safety_floor, f)
    Process.put(:safety_issued, %{})

    try do
      {history, _state, result} = :proper_statem.run_commands(__MODULE__, cmds)
      final = finish(f)

      if result == :ok and final == :ok do
        :ok
      else
        {:failed,
         %{
           result: result,
           final: final,
           collisions: SafetyFloor.collisions(f),
           steps: Enum.zip(:proper_statem.command_names(cmds), Enum.map(history, &elem(&1, 1))),
           leases: Vws.CEC.Interlock.held(f.ws)
         }}
      end
    after
      SafetyFloor.stop(f)
      Process.delete(:safety_floor)
      Process.delete(:safety_issued)
    end
  end

  # The end of a sequence: heal everything, let every command finish, look again.
  defp finish(f) do
    heal()

    with :ok <- settle(),
         true <- SafetyFloor.wait_until(fn -> not MHS.busy?(f.mhs) end, @stuck_ms) || :mhs_stuck,
         :ok <- no_collisions(f) do
      :ok
    end
  end

  ## The steps (each returns :ok or what went wrong)

  @doc "Hands a command to a partition, after its previous one has ended."
  def wc(partition, text) do
    f = floor()

    with :ok <- ended(partition) do
      case SafetyFloor.dispatch(f, partition, text) do
        {:busy, n} ->
          {:busy, partition, n}

        number ->
          Process.put(:safety_issued, Map.put(issued(), partition, {number, text}))
          no_collisions(f)
      end
    end
  end

  @doc "Asks the material-handling system for a move (it runs on its own)."
  def mhs(tray, direction) do
    f = floor()
    :ok = MHS.request(f.mhs, tray, direction)
    no_collisions(f)
  end

  @doc """
  The operator sends a program from the machine's panel (it is stored, never started). Sent in
  a process of its own: the GE-2000 waits for the line while MONARCH may be using it.
  """
  def from_machine(name) do
    f = floor()
    _ = GE2000.put_program(f.ge2000, "000200.PRO", "%\nO200\nN10 M30\n%\n")
    spawn(fn -> GE2000.send_program(f.ge2000, name, 2_000) end)
    no_collisions(f)
  end

  @doc """
  The operator asks the CEC for a program from the machine's panel (a remote request: it is
  filed, never started). In a process of its own, as `from_machine/1`.
  """
  def remote_request(number, version) do
    f = floor()
    spawn(fn -> GE2000.Panel.request_program(f.ge2000, number, version, 2_000) end)
    no_collisions(f)
  end

  @doc "Injects one fault."
  def fault(fault) do
    f = floor()
    inject(f, fault)
    no_collisions(f)
  end

  @doc "Clears every fault of the plant, DAQ #1 and the GE-2000."
  def heal do
    f = floor()
    :ok = Plant.clear_fault(f.plant, :all)
    :ok = DAQ.set_fault(f.daq, :none)
    :ok = GE2000.set_fault(f.ge2000, :none)
    no_collisions(f)
  end

  @doc "Lets time pass."
  def pause(ms) do
    Process.sleep(ms)
    no_collisions(floor())
  end

  @doc "Waits for every partition to end its command and checks how each ended."
  def settle do
    f = floor()

    Enum.reduce_while(SafetyFloor.partitions(), :ok, fn p, :ok ->
      case ended(p) do
        :ok -> {:cont, :ok}
        error -> {:halt, error}
      end
    end)
    |> case do
      :ok -> no_collisions(f)
      error -> error
    end
  end

  # The last command given to the partition has ended DONE or ERROR with a reason.
  defp ended(partition) do
    f = floor()

    result =
      case {Map.get(issued(), partition), SafetyFloor.await_idle(f, partition, @stuck_ms)} do
        {_, {:executing, n}} ->
          {:stuck, partition, n}

        {nil, {:ok, _}} ->
          :ok

        {{number, text}, {:ok, {number, :done}}} ->
          count(partition, text, :done)

        {{number, text}, {:ok, {number, {:error, reason}}}} when byte_size(reason) > 0 ->
          count(partition, text, {:error, reason})

        {{number, text}, {:ok, other}} ->
          {:bad_status, partition, number, text, other}
      end

    # checked once: a later look finds nothing new to check
    if result == :ok, do: Process.put(:safety_issued, Map.delete(issued(), partition))
    result
  end

  # Outcomes by command, when the caller keeps count (`:safety_stats` in the process dictionary,
  # a map): the bench prints what the sequences exercised.
  defp count(partition, text, outcome) do
    case Process.get(:safety_stats) do
      %{} = stats ->
        outcome =
          case outcome do
            :done -> :done
            {:error, reason} -> {:error, reason |> String.split(" (") |> hd()}
          end

        Process.put(:safety_stats, Map.update(stats, {partition, text, outcome}, 1, &(&1 + 1)))
        :ok

      _ ->
        :ok
    end
  end

  defp no_collisions(f) do
    case Enum.reject(SafetyFloor.collisions(f), &(&1.kind in @ignored)) do
      [] -> :ok
      collisions -> {:collisions, collisions}
    end
  end

  defp inject(f, {:plant, kind, opts}), do: :ok = Plant.inject_fault(f.plant, kind, opts)
  defp inject(f, :daq_mute), do: DAQ.set_fault(f.daq, :mute)
  defp inject(f, :daq_slow), do: DAQ.set_fault(f.daq, {:delay_ms, 80})
  defp inject(f, :ge_silent), do: GE2000.set_fault(f.ge2000, :silent)
  defp inject(f, :ge_drop_replies), do: GE2000.set_fault(f.ge2000, :drop_replies)
  defp inject(f, :val_fault), do: VAL2.fault(f.robot, -1002, "ARM POWER FAILED")
  defp inject(f, :val_restart), do: VAL2.restart(f.robot)

  defp inject(f, {:kill, partition}) do
    case Vws.CEC.Partition.whereis(f.ws, partition) do
      nil -> :ok
      pid -> Process.exit(pid, :kill)
    end
  end

  defp floor, do: Process.get(:safety_floor)
  defp issued, do: Process.get(:safety_issued)
end
