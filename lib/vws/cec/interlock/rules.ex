defmodule Vws.CEC.Interlock.Rules do
  @moduledoc """
  The one table of the interlocks (seed §2.3.8): for every command of every set — the seed's and
  ours — which work volume it must hold before its device acts, for which reason, and what
  becomes of that lease when the command ends. `Vws.CEC.Partition.run/2` applies it to every
  command, between the grammar and the module's `execute/2`; no partition takes a lease for a
  command on its own.

  | set | command | needs | when it ends |
  |-----|---------|-------|--------------|
  | ROBOT | `DO MOVE`/`MOVES`/`APPRO`/`APPROS`/`DEPART`/`DEPARTS`, `EXECUTE` | the volumes its target lies in, as `:inside` (rules 1a, 2a; Fig. 13) — the module's `volumes/2` | kept: the arm is there; ROBOT gives up those it has left |
  | ROBOT | `DISABLE_TABLE` | `:table` as `:disabled`, on the table's conditions (rule 1a) | kept until `RELEASE_TABLE` |
  | ROBOT | `DISABLE_TRAY1`/`2` | `:tray1`/`:tray2` as `:disabled` (rule 2a) | kept; given back if the tray's lock fails |
  | ROBOT | `RELEASE_TABLE`, `RELEASE_TRAY1`/`2` | gives a volume up (rule 1b, 2b) | — |
  | ROBOT | `WHERE`, `SPEED` | nothing: reads the arm, sets a speed | — |
  | MONARCH | `CYCLE_START`, `DRIP_FEED` | `:table` as `:cycle` (rules 1b, 3b): the machine moves | kept until `RELEASE_TABLE` finds the machine idle, whatever the command's end |
  | MONARCH | `RELEASE_TABLE` | gives the table up once the machine reports IDLE | — |
  | MONARCH | `DOWNLOAD_GE`(…), `UPLOAD_GE`, `COMPARE_GE`(…), `PROGRAM_SELECT`, `PROGRAM_DELETE`, `TABLE`, `STATUS`, `DOWNLOAD_HP`, `UPLOAD_SUN` | nothing: programs, directory, offsets and reports in the control's memory; nothing moves | — |
  | FIXTURE | `OPEN`, `CLOSE` | `:table` as `:vise`, on the table's conditions (rule 3a) | given back when the sensors confirm it (DONE); kept when it fails (rule 3b) |
  | FIXTURE | `DISABLE_TABLE` | `:table` as `:disabled`, on the table's conditions | kept until `RELEASE_TABLE` |
  | FIXTURE | `RELEASE_TABLE` | gives the table up (the vise at rest) | — |
  | GRIPPER, VACUUM, HYDRAULIC | every command | nothing: no rule of §2.3.8 names them | — |

  A program the GE-2000's operator sends from the machine is not a command: it is stored and
  never starts anything, so it needs no volume.

  A command whose kind is missing here is refused, `ERROR NO INTERLOCK RULE FOR <SET> <KIND>`:
  an interlock that cannot be decided denies. `test/vws/cec/interlock_rules_test.exs` walks the
  command sets of `Vws.Codecs.Commands.kinds/0` and fails on any command this table lacks.

  The conditions of a volume (the machine idle and the table parked, rules 1a and 3a) come from
  the partition's optional `conditions/2` callback; the volumes of a `:target` from its
  `volumes/2`. The lease's wait is the partition's `interlock:` options, `timeout` (ms, default
  10 000) and `retry_ms` (250).
  """

  alias Vws.CEC.Interlock

  @type volume :: Interlock.volume()
  @type rule ::
          :none
          | {:gives_up, volume}
          | %{
              take: volume | :target,
              as: atom,
              on_done: :keep | :release,
              on_error: :keep | :release
            }

  defp take(volume, as, on_done, on_error),
    do: %{take: volume, as: as, on_done: on_done, on_error: on_error}

  @doc """
  The rule of a parsed command of `partition`'s set, or `{:error, text}` when the table has
  none (see the moduledoc).

      iex> Vws.CEC.Interlock.Rules.rule(:monarch, :drip_feed)
      {:ok, %{take: :table, as: :cycle, on_done: :keep, on_error: :keep}}
      iex> Vws.CEC.Interlock.Rules.rule(:robot, {:disable_tray, 2})
      {:ok, %{take: :tray2, as: :disabled, on_done: :keep, on_error: :release}}
      iex> Vws.CEC.Interlock.Rules.rule(:vacuum, :on)
      {:ok, :none}
  """
  @spec rule(atom, term) :: {:ok, rule} | {:error, String.t()}
  def rule(partition, command) do
    case do_rule(partition, kind(command), command) do
      nil ->
        {:error,
         "NO INTERLOCK RULE FOR #{Interlock.name(partition)} #{Interlock.name(kind(command))}"}

      rule ->
        {:ok, rule}
    end
  end

  @doc "The kind of a parsed command: the atom, or a tuple's first element (`{:do, …}` → `:do`)."
  @spec kind(term) :: atom
  def kind(command) when is_atom(command), do: command
  def kind(command) when is_tuple(command), do: elem(command, 0)

  # ROBOT (App. I B)
  defp do_rule(:robot, :do, _), do: take(:target, :inside, :keep, :keep)
  defp do_rule(:robot, :execute, _), do: take(:target, :inside, :keep, :keep)
  defp do_rule(:robot, :disable_table, _), do: take(:table, :disabled, :keep, :keep)
  defp do_rule(:robot, :disable_tray, {_, n}), do: take(tray(n), :disabled, :keep, :release)
  defp do_rule(:robot, :release_table, _), do: {:gives_up, :table}
  defp do_rule(:robot, :release_tray, {_, n}), do: {:gives_up, tray(n)}
  defp do_rule(:robot, kind, _) when kind in [:where, :speed], do: :none

  # MONARCH (App. I A, and ours)
  defp do_rule(:monarch, kind, _) when kind in [:cycle_start, :drip_feed],
    do: take(:table, :cycle, :keep, :keep)

  defp do_rule(:monarch, :release_table, _), do: {:gives_up, :table}

  defp do_rule(:monarch, kind, _)
       when kind in [
              :download_ge,
              :upload_ge,
              :compare_ge,
              :program_select,
              :program_delete,
              :table,
              :status,
              :download_hp,
              :upload_sun
            ],
       do: :none

  # FIXTURE (App. I E)
  defp do_rule(:fixture, kind, _) when kind in [:open, :close],
    do: take(:table, :vise, :release, :keep)

  defp do_rule(:fixture, :disable_table, _), do: take(:table, :disabled, :keep, :keep)
  defp do_rule(:fixture, :release_table, _), do: {:gives_up, :table}

  # GRIPPER, VACUUM, HYDRAULIC (App. I D, C, F): no rule of §2.3.8
  defp do_rule(:gripper, kind, _) when kind in [:open, :close, :rotate], do: :none
  defp do_rule(:vacuum, kind, _) when kind in [:on, :off], do: :none
  defp do_rule(:hydraulic, kind, _) when kind in [:clamp_pallet, :release_pallet], do: :none
  defp do_rule(_partition, _kind, _command), do: nil

  defp tray(1), do: :tray1
  defp tray(2), do: :tray2

  @doc """
  Takes what `command`'s rule needs before `module.execute/2` runs, for the partition of `ctx`
  (holder: the partition's name). Returns `{:ok, taken}` — the `{volume, reason}` leases this
  command holds, for `finish/3` — or `{:error, text}` (nothing taken: a command that needs
  several volumes gets all or none).
  """
  @spec acquire(module, term, map) :: {:ok, [{volume, atom}]} | {:error, String.t()}
  def acquire(module, command, ctx) do
    with {:ok, rule} <- rule(ctx.partition, command) do
      case rule do
        %{take: :target, as: as} ->
          with {:ok, volumes} <- module.volumes(command, ctx),
               do: take_all(module, ctx, volumes, as)

        %{take: volume, as: as} ->
          take_all(module, ctx, [volume], as)

        _none_or_gives_up ->
          {:ok, []}
      end
    end
  end

  # All or none: the volumes taken here are given back when one is refused, unless the holder
  # held them for this reason before.
  defp take_all(module, ctx, volumes, as) do
    ws = ctx.workstation
    before = for v <- volumes, Interlock.holds?(ws, v, ctx.partition, as), do: v

    Enum.reduce_while(volumes, {:ok, []}, fn volume, {:ok, taken} ->
      case Interlock.acquire(ws, volume, ctx.partition, option(ctx, :timeout, 10_000),
             as: as,
             check: conditions(module, volume, ctx),
             retry_ms: option(ctx, :retry_ms, 250)
           ) do
        :ok ->
          {:cont, {:ok, [{volume, as} | taken]}}

        {:error, _} = error ->
          for {v, reason} <- taken,
              v not in before,
              do: Interlock.release(ws, v, ctx.partition, reason)

          {:halt, error}
      end
    end)
    |> case do
      {:ok, taken} -> {:ok, Enum.reverse(taken)}
      error -> error
    end
  end

  defp conditions(module, volume, ctx) do
    if function_exported?(module, :conditions, 2),
      do: module.conditions(volume, ctx),
      else: fn -> :ok end
  end

  defp option(ctx, key, default),
    do: ctx.options |> Keyword.get(:interlock, []) |> Keyword.get(key, default)

  @doc """
  What becomes of the leases `acquire/3` took once the command has ended with `result`: each is
  kept or given back as the rule says for a DONE (`on_done`) or an ERROR (`on_error`).
  """
  @spec finish(term, [{volume, atom}], map, :done | {:error, term}) :: :ok
  def finish(_command, [], _ctx, _result), do: :ok

  def finish(command, taken, ctx, result) do
    {:ok, rule} = rule(ctx.partition, command)
    what = if result == :done, do: rule.on_done, else: rule.on_error

    if what == :release,
      do:
        for(
          {v, reason} <- taken,
          do: Interlock.release(ctx.workstation, v, ctx.partition, reason)
        )

    :ok
  end
end
