defmodule Vws.Test.HeldPartition do
  @moduledoc """
  A partition callback module for tests: each command reports `{:executing, pid, number, command}`
  to the test process given as `options: [test: pid]` and then waits for the test to send the
  result (`send(pid, {:result, :done})`), so a test holds a command in flight as long as it likes.
  """
  @behaviour Vws.CEC.Partition.CommandSet

  @impl true
  def device, do: "TEST DEVICE"

  @impl true
  def parse(text) do
    case text do
      "HOLD" <> _ -> {:ok, {:hold, text}}
      "CRASH" -> {:ok, :crash}
      _ -> {:error, :unknown}
    end
  end

  @impl true
  def execute(:crash, _ctx), do: raise("deliberate crash")

  def execute(command, ctx) do
    send(ctx.options[:test], {:executing, self(), ctx.number, command})

    receive do
      {:result, result} -> result
    end
  end
end
