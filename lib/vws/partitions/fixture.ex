defmodule Vws.Partitions.Fixture do
  @moduledoc """
  FIXTURE (seed App. I E, §2.3.8): opens and closes the vise through the valves of DAQ #1
  (`Vws.Partitions.VwsStatus.operate/4`), reads its clamping force, and keeps the table
  interlock flag. Each vise command ends `DONE` only once the sensors confirm it (seed §6: "the
  clamping force exerted by the vise is sufficient to keep the workpiece from moving"):

    * `OPEN` — CLOSE valve off, OPEN valve on; done when the fully-open switch closes. Else
      `ERROR VISE DID NOT OPEN (JAWS d MM APART, FORCE f N)`.
    * `CLOSE` — OPEN valve off, CLOSE valve on; done when the part-present switch is closed and
      the force gauge reads at least `:min_force_n` (default 800 N). Else, by what was read:
      `ERROR VISE FORCE 310 N BELOW 800 N` (a weak clamp), `ERROR PART NOT IN VISE (JAWS CLOSED
      TO 0.0 MM)` (an empty vise: the jaws close on their stop — this ends at once, nothing will
      change), `ERROR VISE DID NOT CLOSE (JAWS 150.0 MM APART)` (a stuck valve),
      `ERROR VISE FORCE 2000 N BUT PART NOT IN VISE` (the part switch disagrees).
    * `DISABLE_TABLE` / `RELEASE_TABLE` — set / clear the table interlock flag for the fixture
      (`table_interlock/3`); the machine tool's cycle start checks it.

  A sensor reading open circuit ends the command `ERROR VISE SENSOR CH nnn OPEN CIRCUIT`; a DAQ
  that does not answer, `ERROR DAQ #1 NOT ANSWERING (…)`.

  Options (`ctx.options`): `:timeout_ms` (default 5000: a full stroke is 1.5 s, the force rise
  0.3 s), `:min_force_n`.
  """
  @behaviour Vws.Partition

  alias Vws.Mailbox
  alias Vws.DAQ.DeviceStatus
  alias Vws.Partitions.VwsStatus

  @min_force_n 800
  # jaws this close together have closed on their own stop
  @closed_on_stop_mm 1.0

  @impl true
  def device, do: "DAQ #1"

  @impl true
  def parse(text), do: Vws.Commands.parse(:fixture, text)

  @impl true
  def execute(:open, ctx) do
    actions = [vise_close_valve: :open, vise_open_valve: :close]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx), fn r ->
      with {:ok, [open, jaw, force]} <-
             VwsStatus.values(r, [:vise_fully_open, :vise_jaw_mm, :vise_force_n], "VISE") do
        if open,
          do: :ok,
          else: {:wait, "VISE DID NOT OPEN (JAWS #{mm(jaw)} MM APART, FORCE #{n(force)} N)"}
      end
    end)
  end

  def execute(:close, ctx) do
    min = Keyword.get(ctx.options, :min_force_n, @min_force_n)
    actions = [vise_open_valve: :open, vise_close_valve: :close]
    signals = [:vise_part_present, :vise_fully_open, :vise_jaw_mm, :vise_force_n]

    VwsStatus.operate(ctx.workstation, actions, timeout(ctx), fn r ->
      with {:ok, [part, open, jaw, force]} <- VwsStatus.values(r, signals, "VISE") do
        cond do
          part and force >= min ->
            :ok

          force >= min ->
            {:wait, "VISE FORCE #{n(force)} N BUT PART NOT IN VISE"}

          not part and jaw < @closed_on_stop_mm ->
            {:fail, "PART NOT IN VISE (JAWS CLOSED TO #{mm(jaw)} MM)"}

          open ->
            {:wait, "VISE DID NOT CLOSE (JAWS #{mm(jaw)} MM APART)"}

          part ->
            {:wait, "VISE FORCE #{n(force)} N BELOW #{min} N"}

          true ->
            {:wait, "VISE DID NOT CLOSE (JAWS #{mm(jaw)} MM APART, FORCE #{n(force)} N)"}
        end
      end
    end)
  end

  def execute(:disable_table, ctx), do: done(table_interlock(ctx.workstation, :fixture, :disable))
  def execute(:release_table, ctx), do: done(table_interlock(ctx.workstation, :fixture, :release))

  defp done(:ok), do: :done
  defp done(error), do: error

  @doc """
  The table interlock flag (seed §2.3.8, Table 3): the mailbox entry `{:interlock, :table}`
  holds who disabled the machine table (`:fixture`, `:robot`, …); no entry means the table is
  released (the same flag ROBOT's DISABLE_TABLE takes, see `Vws.Partitions.Robot`). `:disable`
  takes the flag for `holder` (at once, atomically; again by the same holder is fine) and fails
  `TABLE HELD BY <holder>` when another holder has it; `:release` gives it back (and is fine when
  nobody has it), and fails the same way when another holder has it. The rules that read it (cycle start, robot approach) come with the
  interlock issue.
  """
  @spec table_interlock(Mailbox.workstation(), atom, :disable | :release) ::
          :ok | {:error, String.t()}
  def table_interlock(ws, holder, :disable) do
    table = Mailbox.table(ws)

    if :ets.insert_new(table, {{:interlock, :table}, holder}) do
      :ok
    else
      case :ets.lookup(table, {:interlock, :table}) do
        [{_, ^holder}] -> :ok
        [{_, other}] -> {:error, "TABLE HELD BY #{name(other)}"}
        [] -> table_interlock(ws, holder, :disable)
      end
    end
  end

  def table_interlock(ws, holder, :release) do
    table = Mailbox.table(ws)

    case :ets.select_delete(table, [{{{:interlock, :table}, holder}, [], [true]}]) do
      1 ->
        :ok

      0 ->
        case :ets.lookup(table, {:interlock, :table}) do
          [] -> :ok
          [{_, ^holder}] -> table_interlock(ws, holder, :release)
          [{_, other}] -> {:error, "TABLE HELD BY #{name(other)}"}
        end
    end
  end

  @doc "Who holds the table interlock flag, or nil when the table is released."
  @spec table_interlock_holder(Mailbox.workstation()) :: atom | nil
  def table_interlock_holder(ws) do
    case :ets.lookup(Mailbox.table(ws), {:interlock, :table}) do
      [{_, holder}] -> holder
      [] -> nil
    end
  end

  defp name(holder), do: holder |> to_string() |> String.upcase()
  defp timeout(ctx), do: Keyword.get(ctx.options, :timeout_ms, 5_000)
  defp mm(value), do: DeviceStatus.mm(value)
  defp n(value), do: DeviceStatus.newtons(value)
end
