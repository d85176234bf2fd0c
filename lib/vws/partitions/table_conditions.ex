defmodule Vws.Partitions.TableConditions do
  @moduledoc """
  The physical conditions of interlock rules 1a and 3a (seed §2.3.8) — the machine tool idle and
  its table at park — read from the plant, as the `:check` ROBOT and FIXTURE give
  `Vws.CEC.Interlock.acquire/5` for the table's work volume.

  They are read here, beside the partitions, and handed to the interlock as a function: the
  interlock keeps the leases and knows nothing of VWS_STATUS or the mailbox locations it reads.
  """

  alias Vws.Links.DAQ.DeviceStatus
  alias Vws.CEC.Mailbox
  alias Vws.Partitions.VwsStatus

  # the MONARCH device-status location, kept by MONARCH's monitor
  @monarch_location 8

  @doc """
  The conditions of a work volume for the interlock table (`Vws.CEC.Interlock.Rules`, through
  ROBOT's and FIXTURE's `conditions/2`): the table's are `check/2` with the partition's
  `interlock:` options; the other volumes have none.
  """
  @spec conditions(atom, map) :: (() -> :ok | {:error, String.t()})
  def conditions(:table, ctx),
    do: check(ctx.workstation, Keyword.get(ctx.options, :interlock, []))

  def conditions(_volume, _ctx), do: fn -> :ok end

  @doc """
  The conditions of rules 1a and 3a — the machine tool idle and its table at park —
  as a `:check` for `acquire/5`. What cannot be read denies:

    * the `MONARCH` status (location 8, kept by MONARCH's monitor) must say `IDLE` and be at
      most `:machine_stale_ms` old (default 3 000): else `MACHINE ACTIVE`,
      `MACHINE STATUS NO DATA (…)`, `MACHINE STATUS STALE (n MS OLD)`;
    * the park switch must read closed in a poll of DAQ #1 *requested after this call* (so
      after the request was posted), waited for at most `:sensor_timeout_ms` (default 500):
      else `NOT IN PARK POSITION`, `NO DATA (…)` as VWS_STATUS has it, or
      `PARK SWITCH NOT READ (…)`.
  """
  @spec check(Mailbox.workstation(), keyword) :: (() -> :ok | {:error, String.t()})
  def check(ws, opts \\ []) do
    machine_stale = Keyword.get(opts, :machine_stale_ms, 3_000)
    sensor_timeout = Keyword.get(opts, :sensor_timeout_ms, 500)

    fn ->
      with :ok <- machine_idle(ws, machine_stale) do
        table_parked(ws, sensor_timeout)
      end
    end
  end

  defp machine_idle(ws, stale_ms) do
    case Mailbox.get_device(ws, @monarch_location) do
      {"IDLE", age} when age <= stale_ms -> :ok
      {"IDLE", age} -> {:error, "MACHINE STATUS STALE (#{age} MS OLD)"}
      {"ACTIVE", age} when age <= stale_ms -> {:error, "MACHINE ACTIVE"}
      {"ACTIVE", age} -> {:error, "MACHINE STATUS STALE (#{age} MS OLD)"}
      {nil, _} -> {:error, "MACHINE STATUS NO DATA"}
      {other, _} when is_binary(other) -> {:error, "MACHINE STATUS " <> other}
      {other, _} -> {:error, "MACHINE STATUS " <> Vws.Codecs.WC.Words.of(other)}
    end
  end

  defp table_parked(ws, timeout_ms) do
    since = System.monotonic_time(:microsecond)

    case VwsStatus.await(ws, since, timeout_ms, fn r ->
           case DeviceStatus.table(r) do
             "TABLE IN PARK POSITION" -> :ok
             text -> {:fail, text}
           end
         end) do
      :ok -> :ok
      {:error, "TABLE " <> text} -> {:error, text}
      {:error, "NO DATA " <> _ = text} -> {:error, text}
      # "DAQ #1 NOT ANSWERING (NO FRESH READING IN 500 MS)": the first words say it
      {:error, why} -> {:error, "PARK SWITCH NOT READ (#{why |> String.split(" (") |> hd()})"}
    end
  end
end
