defmodule Vws.Test.ObedientPartition do
  @moduledoc """
  A partition callback module for these tests: takes any text. With `options: [test: pid]` each
  command reports `{:executing, pid, number, text}` and waits for `{:result, result}`; without,
  it ends `DONE` at once — except a text `FAIL <reason>`, which ends `ERROR <reason>`.
  """
  @behaviour Vws.CEC.Partition.CommandSet

  @impl true
  def device, do: "TEST DEVICE"

  @impl true
  def parse(text), do: {:ok, text}

  @impl true
  def execute("FAIL " <> reason, _ctx), do: {:error, reason}

  def execute(text, ctx) do
    case ctx.options[:test] do
      nil ->
        :done

      test ->
        send(test, {:executing, self(), ctx.number, text})

        receive do
          {:result, result} -> result
        end
    end
  end

  @doc "Partition options giving every command set to this module."
  def partitions(options \\ []) do
    for p <- [:robot, :monarch, :gripper, :fixture, :vacuum, :hydraulic],
        do: {p, [module: __MODULE__, interlocks: :off, link: :test, options: options]}
  end
end
