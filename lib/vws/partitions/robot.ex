defmodule Vws.Partitions.Robot do
  @moduledoc """
  ROBOT: the partition that runs the robot command set (seed App. I B, §4.4) on the VAL II,
  through the logical-unit layer `Vws.VAL` (`ctx.link` is the `Vws.VAL` process).

  | WC command | what runs | DONE when |
  |------------|-----------|-----------|
  | `WHERE` | monitor `WHERE` | the response came; it is written to `WHERE_ROBOT` (device-status location 9) as `x/y/z/θ/A/T/j1/…/j6` |
  | `SPEED N` | monitor `SPEED N` | the response came |
  | `DO MOVE loc`, `DO MOVES loc` | the same, in VAL II syntax (`loc:TRANS(x,y,z,o,a,t)`) | MOTION COMPLETE |
  | `DO APPRO loc/d`, `DO APPROS loc/d` | `DO APPRO loc, d` … | MOTION COMPLETE |
  | `DO DEPART d`, `DO DEPARTS d` | the same | MOTION COMPLETE |
  | `EXECUTE name` | monitor `EXECUTE name` | PROGRAM COMPLETE |
  | `DISABLE_TRAYn`, `RELEASE_TRAYn`, `DISABLE_TABLE`, `RELEASE_TABLE` | interlock flags (below) | the flag is set / cleared |

  The WC writes the robot's commands with `/` between arguments; VAL II wants commas, so motion
  instructions are rewritten from the parsed command (`Vws.Commands`), never passed through.

  An error numbered by the controller ends the command `ERROR <code> <text>` (e.g.
  `ERROR -301 UNDEFINED LOCATION MV9`); trouble on the way ends it `ERROR VAL II <what>`:
  `TIMEOUT`, `LINK DOWN`, `RESTARTED` (the controller restarted mid-command), `NO RESPONSE`,
  `BAD RESPONSE`, `COMMAND TOO LONG`. A command that ended in error is never sent again by the
  CEC: the WC decides.

  ## Interlock flags (seed §2.3.8, Table 3)

  In the workstation's mailbox table (`Vws.Mailbox.table/1`), key `{:interlock, {:tray, n}}` or
  `{:interlock, :table}`, value the holder — `{{:interlock, {:tray, 1}}, :robot}`. DISABLE takes
  the flag atomically (`:ets.insert_new`): it is DONE when the flag is free or already the
  robot's, `ERROR TRAY n HELD BY <holder>` when another holder has it. RELEASE clears it when it
  is the robot's (DONE also when nobody holds it), `ERROR … HELD BY <holder>` otherwise. The
  retrying lease and the checks before each motion come with the safety work.

  ## Options (`ctx.options`)

    * `:tray_lock` — `fun(n, :lock | :release) :: :ok | {:error, reason}`, the seam for the DAQ
      relay that physically locks tray `n` out of the material-handling system; called after
      the flag is taken (a failure gives it back) and before it is cleared. Without it only the
      flag is set.
    * `:reinit` — `true`: re-initialise the DDCMP link after every command that went to the
      VAL II, as the seed's ROBOT program does (seed §4.3.2). Default `false`.
    * `:command_timeout` (default 10 s), `:motion_timeout` (120 s), `:program_timeout` (600 s),
      in ms.
  """
  @behaviour Vws.Partition

  alias Vws.Mailbox

  @where_location 9

  @impl true
  def device, do: "VAL II"

  @impl true
  def parse(text), do: Vws.Commands.parse(:robot, text)

  @impl true
  def execute({:disable_tray, n}, ctx), do: disable(ctx, {:tray, n})
  def execute({:release_tray, n}, ctx), do: release(ctx, {:tray, n})
  def execute(:disable_table, ctx), do: disable(ctx, :table)
  def execute(:release_table, ctx), do: release(ctx, :table)

  def execute(command, ctx) do
    result = run(command, ctx)

    if ctx.options[:reinit] do
      case Vws.VAL.reinitialise(ctx.link) do
        :ok -> :ok
        {:error, :busy} -> :ok
      end
    end

    result
  end

  defp run(:where, ctx) do
    with {:ok, text} <- val(Vws.VAL.command(ctx.link, "WHERE", timeout(ctx, :command))),
         {:ok, %{world: world, joints: joints}} <- where(text) do
      Mailbox.put_device(ctx.workstation, @where_location, where_robot(world ++ joints))
      :done
    end
  end

  defp run({:speed, n}, ctx) do
    with {:ok, _} <-
           val(Vws.VAL.command(ctx.link, "SPEED " <> number(n), timeout(ctx, :command))),
         do: :done
  end

  defp run({:execute, name}, ctx) do
    with {:ok, _} <- val(Vws.VAL.command(ctx.link, "EXECUTE " <> name, timeout(ctx, :program))),
         do: :done
  end

  defp run({:do, _, _} = motion, ctx), do: motion(motion, ctx)
  defp run({:do, _, _, _} = motion, ctx), do: motion(motion, ctx)

  defp motion(command, ctx) do
    with {:ok, _} <- val(Vws.VAL.command(ctx.link, instruction(command), timeout(ctx, :motion))),
         do: :done
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
    case Vws.VAL.parse_where(text) do
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
  defp val({:error, other}), do: {:error, "VAL II " <> String.upcase(inspect(other))}

  defp timeout(ctx, :command), do: Keyword.get(ctx.options, :command_timeout, 10_000)
  defp timeout(ctx, :motion), do: Keyword.get(ctx.options, :motion_timeout, 120_000)
  defp timeout(ctx, :program), do: Keyword.get(ctx.options, :program_timeout, 600_000)

  ## Interlock flags

  @doc "Who holds an interlock flag (`{:tray, n}` or `:table`) of a workstation, or nil."
  @spec interlock_holder(term, {:tray, 1 | 2} | :table) :: atom | nil
  def interlock_holder(ws, what) do
    case :ets.lookup(Mailbox.table(ws), {:interlock, what}) do
      [{_, holder}] -> holder
      [] -> nil
    end
  end

  defp disable(ctx, what) do
    table = Mailbox.table(ctx.workstation)
    key = {:interlock, what}

    if :ets.insert_new(table, {key, :robot}) do
      case tray_lock(ctx, what, :lock) do
        :ok ->
          :done

        {:error, reason} ->
          :ets.delete_object(table, {key, :robot})
          {:error, "#{name(what)} LOCK FAILED #{reason}"}
      end
    else
      case interlock_holder(ctx.workstation, what) do
        :robot -> :done
        # released between the two calls: take it now
        nil -> disable(ctx, what)
        holder -> held(what, holder)
      end
    end
  end

  defp release(ctx, what) do
    table = Mailbox.table(ctx.workstation)

    case interlock_holder(ctx.workstation, what) do
      nil ->
        :done

      :robot ->
        case tray_lock(ctx, what, :release) do
          :ok ->
            :ets.delete_object(table, {{:interlock, what}, :robot})
            :done

          {:error, reason} ->
            {:error, "#{name(what)} RELEASE FAILED #{reason}"}
        end

      holder ->
        held(what, holder)
    end
  end

  defp tray_lock(ctx, {:tray, n}, action) do
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

  defp held(what, holder),
    do: {:error, "#{name(what)} HELD BY #{holder |> to_string() |> String.upcase()}"}

  defp name({:tray, n}), do: "TRAY #{n}"
  defp name(:table), do: "TABLE"
end
