defmodule Vws.LogLimit do
  @moduledoc """
  Repeated warnings, logged by condition instead of by occurrence: one line when a condition
  starts, none while it goes on (the occurrences are counted), one line when it ends — with how
  many times it occurred and for how long.

      # each failed poll of an unreachable DAQ #1 (50 a second):
      Vws.LogLimit.warning(:stale, "VWS_STATUS: readings are stale: DAQ #1 NOT CONNECTED")
      # the first good one:
      Vws.LogLimit.clear(:stale, "VWS_STATUS: DAQ #1 answers again")

  logs

      [warning] VWS_STATUS: readings are stale: DAQ #1 NOT CONNECTED
      [warning] VWS_STATUS: DAQ #1 answers again (after 1,515 occurrences over 30.3 s)

  The end is logged at the start's level, so that where one line of the pair is shown the other
  is too. `clear/2` of a condition that is not on logs nothing. The conditions are the calling
  process's own (kept in its process dictionary under `{Vws.LogLimit, key}`): a process that
  restarts starts afresh, and two links with the same trouble each say so once. The logger
  metadata is the caller's (workstation, partition).
  """

  require Logger

  @doc """
  An occurrence of condition `key`: logs `message` (a string, or a function returning one,
  called only when it is logged) if the condition was not on, else only counts it.
  Returns `:logged` or `:counted`.
  """
  @spec warning(term, String.t() | (() -> String.t()), Logger.level()) :: :logged | :counted
  def warning(key, message, level \\ :warning) do
    case Process.get({__MODULE__, key}) do
      nil ->
        Process.put({__MODULE__, key}, {1, System.monotonic_time(:millisecond), level})
        Logger.log(level, text(message))
        :logged

      {n, since, level} ->
        Process.put({__MODULE__, key}, {n + 1, since, level})
        :counted
    end
  end

  @doc """
  Condition `key` is over: if it was on, logs `message` with the count and the time it lasted
  (`"… (after 3 occurrences over 1.2 s)"`) and returns `:logged`; else `:off`.
  """
  @spec clear(term, String.t() | (() -> String.t())) :: :logged | :off
  def clear(key, message) do
    case Process.delete({__MODULE__, key}) do
      nil ->
        :off

      {n, since, level} ->
        ms = System.monotonic_time(:millisecond) - since
        Logger.log(level, "#{text(message)} (after #{occurrences(n)} over #{seconds(ms)})")
        :logged
    end
  end

  @doc "Whether condition `key` is on in the calling process."
  @spec on?(term) :: boolean
  def on?(key), do: Process.get({__MODULE__, key}) != nil

  defp text(message) when is_function(message, 0), do: message.()
  defp text(message) when is_binary(message), do: message

  defp occurrences(1), do: "1 occurrence"
  defp occurrences(n), do: "#{thousands(n)} occurrences"

  defp thousands(n),
    do: n |> Integer.to_string() |> String.replace(~r/\B(?=(\d{3})+$)/, ",")

  defp seconds(ms), do: :erlang.float_to_binary(ms / 1000, decimals: 1) <> " s"
end
