defmodule Vws.Partitions.Robot do
  @moduledoc """
  ROBOT: the partition that runs the robot command set (seed App. I B, §4.4) on the VAL II,
  through the logical-unit layer `Vws.Links.VAL` (`ctx.link` is the `Vws.Links.VAL` process).

  | WC command | what runs | DONE when |
  |------------|-----------|-----------|
  | `WHERE` | monitor `WHERE` | the response came; it is written to `WHERE_ROBOT` (device-status location 9) as `x/y/z/θ/A/T/j1/…/j6` |
  | `SPEED N` | monitor `SPEED N` | the response came |
  | `DO MOVE loc`, `DO MOVES loc` | the same, in VAL II syntax (`loc:TRANS(x,y,z,o,a,t)`) | MOTION COMPLETE |
  | `DO APPRO loc/d`, `DO APPROS loc/d` | `DO APPRO loc, d` … | MOTION COMPLETE |
  | `DO DEPART d`, `DO DEPARTS d` | the same | MOTION COMPLETE |
  | `EXECUTE name` | monitor `EXECUTE name` | PROGRAM COMPLETE |
  | `DISABLE_TRAYn`, `RELEASE_TRAYn`, `DISABLE_TABLE`, `RELEASE_TABLE` | interlocks (below) | the lease is taken / given up |

  The WC writes the robot's commands with `/` between arguments; VAL II wants commas, so motion
  instructions are rewritten from the parsed command (`Vws.Codecs.Commands`), never passed through.

  An error numbered by the controller ends the command `ERROR <code> <text>` (e.g.
  `ERROR -301 UNDEFINED LOCATION MV9`); trouble on the way ends it `ERROR VAL II <what>`:
  `TIMEOUT`, `LINK DOWN`, `RESTARTED` (the controller restarted mid-command), `NO RESPONSE`,
  `BAD RESPONSE`, `COMMAND TOO LONG`. A command that ended in error is never sent again by the
  CEC: the WC decides.

  ## Interlocks (seed §2.3.8, §4.4 Fig. 13)

  Through `Vws.CEC.Interlock`, with ROBOT as holder `:robot`; the leases a command needs are
  taken by the one interlock table (`Vws.CEC.Interlock.Rules`) before the arm moves, from the
  volumes and conditions this module gives (`volumes/2`, `conditions/2`):

    * `DISABLE_TRAYn` takes tray n's volume (`:tray1`, `:tray2`; re-tried while the
      material-handling system holds it — rule 2a) and then locks the tray through the
      `:tray_lock` seam; a lock that fails gives the lease back. `RELEASE_TRAYn` unlocks the tray
      and gives its lease up (rule 2b: the MHS may move it again).
    * `DISABLE_TABLE` takes the table's volume, shared with FIXTURE but never with MONARCH's
      cycle, on the conditions of rule 1a: the machine idle and the table parked, as read
      (`Vws.Partitions.TableConditions.check/2`). `RELEASE_TABLE` gives it up (rule 1b: a cycle may
      start).
    * Every `DO MOVE`/`MOVES`/`APPRO`/`APPROS` into a volume first takes that volume for the arm
      (reason `:inside`) by the same procedure and on the same conditions, unless it is held
      already (then the conditions are read again) — the device lock-out of Fig. 13 before the
      robot leaves SAFE for a work volume. Which volume a location lies in comes from
      `priv/work_volumes.exs` (`Vws.CEC.Interlock.WorkVolumes`); `loc:TRANS(…)` lies in the volume
      of `loc`; a location that is not listed is refused. `DEPART`/`DEPARTS` stays in the volume
      the arm is in. `EXECUTE name` takes the volumes the program is listed to enter.
    * When a motion completes, the arm's leases on the volumes it has left are given up; when
      one fails (an error, a restart, a timeout) the arm may be anywhere between, so it keeps
      every lease it had and took until a motion completes again. `RELEASE_TABLE` or
      `RELEASE_TRAYn` while the arm is in that volume is refused:
      `ERROR INTERLOCK ROBOT IN TABLE VOLUME`.

  A request that times out ends `ERROR INTERLOCK <VOLUME> HELD BY <HOLDER>` or
  `ERROR INTERLOCK TABLE <condition>` (`MACHINE ACTIVE`, `NOT IN PARK POSITION`,
  `MACHINE STATUS STALE (n MS OLD)`, …). The leases live in the mailboxes: a restarted ROBOT
  finds them.

  ## Options (`ctx.options`)

    * `:tray_lock` — `fun(n, :lock | :release) :: :ok | {:error, reason}`, the seam for the DAQ
      relay that physically locks tray `n` out of the material-handling system; called after
      the lease is taken (a failure gives it back) and before it is given up. Without it only
      the lease is taken.
    * `:reinit` — `true`: re-initialise the DDCMP link after every command that went to the
      VAL II, as the seed's ROBOT program does (seed §4.3.2). Default `false`.
    * `:command_timeout` (default 10 s), `:motion_timeout` (120 s), `:program_timeout` (600 s),
      in ms.
    * `:interlock` — `timeout` (ms a lease is tried for, default 10 000), `retry_ms` (250),
      `machine_stale_ms`, `sensor_timeout_ms` (see `Vws.Partitions.TableConditions.check/2`).
    * `:work_volumes` — a map or a path in the shape of `priv/work_volumes.exs` (the default).
  """
  @behaviour Vws.CEC.Partition.CommandSet

  alias Vws.CEC.{Interlock, Mailbox}
  alias Vws.Links.VAL
  alias Vws.CEC.Interlock.WorkVolumes

  @where_location 9

  @impl true
  def device, do: "VAL II"

  @impl true
  def parse(text), do: Vws.Codecs.Commands.parse(:robot, text)

  @impl true
  def execute({:disable_tray, n}, ctx), do: disable_tray(ctx, n)
  def execute({:release_tray, n}, ctx), do: release_volume(ctx, tray(n))
  def execute(:disable_table, ctx), do: disable_table(ctx)
  def execute(:release_table, ctx), do: release_volume(ctx, :table)

  def execute(command, ctx) do
    result = run(command, ctx)

    if ctx.options[:reinit] do
      case VAL.reinitialise(ctx.link) do
        :ok -> :ok
        {:error, :busy} -> :ok
      end
    end

    result
  end

  defp run(:where, ctx) do
    with {:ok, text} <- val(VAL.request(ctx.link, {:response, "WHERE"}, timeout(ctx, :command))),
         {:ok, %{world: world, joints: joints}} <- where(text) do
      Mailbox.put_device(ctx.workstation, @where_location, where_robot(world ++ joints))
      :done
    end
  end

  defp run({:speed, n}, ctx) do
    with {:ok, _} <-
           val(VAL.request(ctx.link, {:response, "SPEED " <> number(n)}, timeout(ctx, :command))),
         do: :done
  end

  defp run({:execute, name}, ctx) do
    with {:ok, %{ends: ends}} <- WorkVolumes.program(work_volumes(ctx), name),
         {:ok, _} <- val(VAL.execute(ctx.link, name, timeout(ctx, :program))) do
      arrived(ctx, ends)
    end
  end

  defp run({:do, _, _} = motion, ctx), do: motion(motion, ctx)
  defp run({:do, _, _, _} = motion, ctx), do: motion(motion, ctx)

  # The volumes were taken by the interlock table (Vws.CEC.Interlock.Rules, through volumes/2).
  defp motion(command, ctx) do
    with {:ok, target} <- target(command, ctx),
         # what it waits for is known from the parsed command, not read back from its text
         {:ok, _} <-
           val(
             VAL.request(
               ctx.link,
               {:motion_complete, instruction(command)},
               timeout(ctx, :motion)
             )
           ) do
      arrived(ctx, target)
    end
  end

  @doc """
  The VAL II text of a parsed motion instruction.

      iex> Vws.Partitions.Robot.instruction({:do, :move, {:trans, "MV1", [63.5, 0.0, 0.0, 90.0, -90.0, 0.0]}})
      "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"
      iex> Vws.Partitions.Robot.instruction({:do, :appros, "TRAY1", 50.0})
      "DO APPROS TRAY1, 50"
  """
  @spec instruction(tuple) :: String.t()
  def instruction({:do, kind, loc}) when kind in [:move, :moves],
    do: "DO #{word(kind)} #{location(loc)}"

  def instruction({:do, kind, dist}) when kind in [:depart, :departs],
    do: "DO #{word(kind)} #{number(dist)}"

  def instruction({:do, kind, loc, dist}) when kind in [:appro, :appros],
    do: "DO #{word(kind)} #{location(loc)}, #{number(dist)}"

  @doc """
  The `WHERE_ROBOT` status text of the 12 WHERE numbers, one decimal each.

      iex> Vws.Partitions.Robot.where_robot([800.0, 0.0, 1200.0, 0.0, 180.0, 0.0, 0.0, 29.36, 267.88, 180.0, 150.64, -0.01])
      "800.0/0.0/1200.0/0.0/180.0/0.0/0.0/29.4/267.9/180.0/150.6/0.0"
  """
  @spec where_robot([float]) :: String.t()
  def where_robot(numbers) do
    Enum.map_join(numbers, "/", fn v ->
      case :erlang.float_to_binary(v * 1.0, decimals: 1) do
        "-0.0" -> "0.0"
        text -> text
      end
    end)
  end

  defp where(text) do
    case VAL.parse_where(text) do
      {:ok, where} -> {:ok, where}
      {:error, _} -> {:error, "VAL II BAD WHERE RESPONSE"}
    end
  end

  defp word(kind), do: kind |> Atom.to_string() |> String.upcase()

  defp location({:trans, name, values}),
    do: "#{name}:TRANS(#{Enum.map_join(values, ",", &number/1)})"

  defp location(name) when is_binary(name), do: name

  defp number(v) when is_integer(v), do: Integer.to_string(v)

  defp number(v) when is_float(v) do
    if v == Float.round(v) and abs(v) < 1.0e15,
      do: v |> trunc() |> Integer.to_string(),
      else: :erlang.float_to_binary(v, [:short])
  end

  defp val({:ok, text}), do: {:ok, text}
  defp val({:error, {code, text}}) when is_integer(code), do: {:error, "#{code} #{text}"}
  defp val({:error, :timeout}), do: {:error, "VAL II TIMEOUT"}
  defp val({:error, {:link_down, _}}), do: {:error, "VAL II LINK DOWN"}
  defp val({:error, :peer_restarted}), do: {:error, "VAL II RESTARTED"}
  defp val({:error, :no_response}), do: {:error, "VAL II NO RESPONSE"}
  defp val({:error, {:bad_response, _}}), do: {:error, "VAL II BAD RESPONSE"}
  defp val({:error, {:bad_command, _}}), do: {:error, "VAL II COMMAND TOO LONG"}
  defp val({:error, {:async_error, text}}), do: {:error, "VAL II ERROR " <> text}
  defp val({:error, other}), do: {:error, "VAL II " <> Vws.Codecs.WC.Words.of(other)}

  defp timeout(ctx, :command), do: Keyword.get(ctx.options, :command_timeout, 10_000)
  defp timeout(ctx, :motion), do: Keyword.get(ctx.options, :motion_timeout, 120_000)
  defp timeout(ctx, :program), do: Keyword.get(ctx.options, :program_timeout, 600_000)

  ## Interlocks

  # The volume a motion ends in: a location's, or :here for a DEPART.
  defp target({:do, kind, _dist}, _ctx) when kind in [:depart, :departs], do: {:ok, :here}
  defp target({:do, _kind, loc}, ctx), do: WorkVolumes.location(work_volumes(ctx), loc)
  defp target({:do, _kind, loc, _dist}, ctx), do: WorkVolumes.location(work_volumes(ctx), loc)

  @doc """
  The work volumes a motion or a program enters (Fig. 13's device lock-out), for the interlock
  table (`Vws.CEC.Interlock.Rules`), which takes them all, as `:inside`, before the arm moves:
  a location's volume (none for `SAFE` or a `DEPART`), a program's `enters`.
  """
  @impl true
  def volumes({:execute, name}, ctx) do
    with {:ok, %{enters: volumes}} <- WorkVolumes.program(work_volumes(ctx), name),
         do: {:ok, volumes}
  end

  def volumes(motion, ctx) do
    case target(motion, ctx) do
      {:ok, target} when target in [:here, :safe] -> {:ok, []}
      {:ok, volume} -> {:ok, [volume]}
      error -> error
    end
  end

  @doc "The conditions of rule 1a for the table (`Vws.Partitions.TableConditions`); none elsewhere."
  @impl true
  defdelegate conditions(volume, ctx), to: Vws.Partitions.TableConditions

  # The motion completed: the arm is in `target` (or where it was, for :here) and has left
  # every other volume.
  defp arrived(_ctx, :here), do: :done

  defp arrived(ctx, target) do
    for volume <- inside(ctx),
        volume != target,
        do: Interlock.release(ctx.workstation, volume, :robot, :inside)

    :done
  end

  defp inside(ctx) do
    for %{holder: :robot, volume: v, reasons: reasons} <- Interlock.held(ctx.workstation),
        :inside in reasons,
        do: v
  end

  # The table was taken as :disabled by the interlock table; nothing more to do.
  defp disable_table(_ctx), do: :done

  # The tray was taken as :disabled by the interlock table, which gives it back if the lock fails.
  defp disable_tray(ctx, n) do
    case tray_lock(ctx, tray(n), :lock) do
      :ok -> :done
      {:error, reason} -> {:error, "TRAY #{n} LOCK FAILED #{reason}"}
    end
  end

  defp release_volume(ctx, volume) do
    if Interlock.holds?(ctx.workstation, volume, :robot, :inside) do
      {:error, "INTERLOCK ROBOT IN #{Interlock.name(volume)} VOLUME"}
    else
      case tray_lock(ctx, volume, :release) do
        :ok ->
          Interlock.release(ctx.workstation, volume, :robot, :disabled)
          :done

        {:error, reason} ->
          {:error, "#{display(volume)} RELEASE FAILED #{reason}"}
      end
    end
  end

  defp work_volumes(ctx) do
    case Keyword.get(ctx.options, :work_volumes) do
      nil -> WorkVolumes.default()
      source -> WorkVolumes.load(source)
    end
  end

  defp tray(1), do: :tray1
  defp tray(2), do: :tray2

  defp display(:tray1), do: "TRAY 1"
  defp display(:tray2), do: "TRAY 2"
  defp display(:table), do: "TABLE"

  defp tray_lock(ctx, volume, action) when volume in [:tray1, :tray2] do
    n = if volume == :tray1, do: 1, else: 2

    case Keyword.get(ctx.options, :tray_lock) do
      nil ->
        :ok

      fun ->
        case fun.(n, action) do
          :ok -> :ok
          {:error, reason} -> {:error, reason |> to_string() |> String.upcase()}
        end
    end
  end

  defp tray_lock(_ctx, :table, _action), do: :ok
end
