defmodule Vws.Test.FailureRecap do
  @moduledoc """
  The failed tests named again after the suite's summary, without their captured logs.

  ExUnit prints a failure when it happens, with everything logged while its test ran. With
  `capture_log: true` and sixteen modules at once, that is every workstation's log of those
  seconds: one failure is hundreds of lines, and a CI page that keeps only the end of the output
  showed "2 failures" under a wall of other tests' log lines, without the name of either.

  This formatter keeps each failure's test, place and error (its first lines); `recap/0`, an
  `ExUnit.after_suite/1` callback (`test/test_helper.exs`), prints them after ExUnit's own summary,
  so they close the output. It changes nothing about what runs or how it is judged.
  """

  use GenServer

  @key {__MODULE__, :failures}
  @lines 30

  @impl true
  def init(_opts) do
    :persistent_term.put(@key, [])
    {:ok, 0}
  end

  @impl true
  def handle_cast({:test_finished, %ExUnit.Test{state: {:failed, _}} = test}, count),
    do: keep(count + 1, &entry(test, &1))

  def handle_cast({:module_finished, %ExUnit.TestModule{state: {:failed, _}} = module}, count),
    do: keep(count + 1, &module_entry(module, &1))

  def handle_cast(_event, count), do: {:noreply, count}

  # the failure numbered `count`, its text made by `text`, kept for the recap
  defp keep(count, text) do
    :persistent_term.put(@key, [text.(count) | :persistent_term.get(@key, [])])
    {:noreply, count}
  end

  @doc "Prints the failures kept (nothing when there were none)."
  def recap do
    case :persistent_term.get(@key, []) do
      [] ->
        :ok

      failures ->
        IO.puts(
          "\nThe failures again, without their logs (#{length(failures)}):\n\n" <>
            Enum.join(Enum.reverse(failures), "\n")
        )
    end
  end

  defp module_entry(%ExUnit.TestModule{state: {:failed, failures}} = module, count),
    do: cut(ExUnit.Formatter.format_test_all_failure(module, failures, count, 80, &plain/2))

  defp entry(test, count) do
    {:failed, failures} = test.state
    # the captured log is what makes a failure long; its place and error are what name it
    test = %{test | logs: ""}
    cut(ExUnit.Formatter.format_test_failure(test, failures, count, 80, &plain/2))
  end

  defp cut(text) do
    lines = String.split(text, "\n")

    if length(lines) > @lines do
      Enum.join(
        Enum.take(lines, @lines) ++ ["     … (#{length(lines) - @lines} more lines)"],
        "\n"
      )
    else
      text
    end
  end

  # ExUnit.Formatter asks its formatter callback for colours and widths; plain text here
  defp plain(:diff_enabled?, _), do: false
  defp plain(_key, value), do: value
end
