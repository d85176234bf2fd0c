defmodule Vws.Test.Eventually do
  @moduledoc "Polls a condition with a generous deadline instead of sleeping a guessed time."

  @doc "True as soon as `fun.()` is truthy (asked every `interval` ms); false when `timeout` ms pass first."
  def eventually(fun, timeout \\ 5_000, interval \\ 10) do
    deadline = System.monotonic_time(:millisecond) + timeout
    poll(fun, deadline, interval)
  end

  defp poll(fun, deadline, interval) do
    cond do
      fun.() -> true
      System.monotonic_time(:millisecond) > deadline -> false
      true -> Process.sleep(interval) && poll(fun, deadline, interval)
    end
  end
end
