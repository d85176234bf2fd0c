defmodule Vws.Test.Eventually do
  @moduledoc "Polls a condition with a generous deadline instead of sleeping a guessed time."

  @doc "True as soon as `fun.()` is truthy; false when `timeout` ms pass first."
  def eventually(fun, timeout \\ 5_000) do
    deadline = System.monotonic_time(:millisecond) + timeout
    poll(fun, deadline)
  end

  defp poll(fun, deadline) do
    cond do
      fun.() -> true
      System.monotonic_time(:millisecond) > deadline -> false
      true -> Process.sleep(10) && poll(fun, deadline)
    end
  end
end
