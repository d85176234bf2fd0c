defmodule Vws.Peers.WC.Runner do
  @moduledoc """
  Runs a `Vws.Peers.WC.Script` through a `Vws.Peers.WC.Client`, as the workstation controller would: step by
  step, each command followed by the seed's polling rule (its status asked until its number
  appears, `DONE` to go on), each `EXPECT` checked on the device. The first step that does not
  succeed stops the script, with the reason — for a command, the CEC's own `ERROR <reason>`.

  Every step is announced in the client's event log (`Vws.Peers.WC.Client.note/2`) before its lines,
  so a printed log reads as script line, string, reply, status answers.

  Options:

    * `:timeout` — ms a command or a `WAIT` may take (default 60 000; a script's `TIMEOUT` line
      changes it from there on)
    * `:expect_grace` — ms an `EXPECT` keeps asking before it fails (default 2 000), as device
      readings follow a command by a scan or two
    * `:poll_interval` — ms between status queries (default 100)
    * `:transfer_retries` — how many times a program transfer (`DOWNLOAD`, `UPLOAD`) that broke
      off on the link, or whose whole program did not arrive as sent (its CRC), is made again,
      from the start and as a new command (default 2): the CEC ends the broken one `ERROR` and
      keeps nothing of it, and a transfer moves nothing

      summary = Vws.Peers.WC.Runner.run(client, script)
      summary.result     #=> :completed | :stopped
  """

  alias Vws.Peers.WC.{Client, ClientError, Script}
  alias Vws.Peers.WC.Runner.Summary

  @doc "Runs `script` to its end or its first failure; returns the summary."
  @spec run(Client.client(), Script.t(), keyword) :: Summary.t()
  def run(client, %Script{steps: steps} = script, opts \\ []) do
    started = now()
    before = Client.info(client).counters
    total = length(steps)

    settings = %{
      timeout: Keyword.get(opts, :timeout, 60_000),
      grace: Keyword.get(opts, :expect_grace, 2_000),
      poll: Keyword.get(opts, :poll_interval, 100),
      transfer_retries: Keyword.get(opts, :transfer_retries, 2)
    }

    {outcome, done, uploads, _settings} =
      steps
      |> Enum.with_index(1)
      |> Enum.reduce_while({:completed, 0, [], settings}, fn {step, i}, {_, done, ups, set} ->
        :ok = Client.note(client, "step #{i} of #{total}, line #{step.line}: #{step.source}")

        case run_step(step.op, client, set) do
          {:ok, set} ->
            {:cont, {:completed, done + 1, ups, set}}

          {:uploaded, lines} ->
            {:cont, {:completed, done + 1, [lines | ups], set}}

          {:error, error} ->
            stop = %{
              step: i,
              line: step.line,
              source: step.source,
              reason: reason(error),
              error: error
            }

            :ok = Client.note(client, "STOPPED at line #{step.line}: #{stop.reason}")
            {:halt, {{:stopped, stop}, done, ups, set}}
        end
      end)

    counters = Client.info(client).counters
    delta = fn key -> counters[key] - before[key] end

    {result, stopped} =
      case outcome do
        :completed -> {:completed, nil}
        {:stopped, stop} -> {:stopped, stop}
      end

    %Summary{
      script: script.path,
      result: result,
      stopped: stopped,
      steps_total: total,
      steps_done: done,
      strings: delta.(:strings),
      commands: delta.(:commands),
      status_queries: delta.(:status_queries),
      resends: delta.(:resends),
      naks: delta.(:naks),
      timeouts: delta.(:timeouts),
      program_lines_sent: delta.(:lines_sent),
      program_lines_received: delta.(:lines_received),
      transfers_broken: delta.(:transfers_broken),
      uploads: Enum.reverse(uploads),
      elapsed_ms: now() - started
    }
  end

  defp run_step({:commands, commands}, client, set) do
    with {:ok, numbered} <- Client.send_commands(client, commands),
         :ok <- await_all(client, numbered, set) do
      {:ok, set}
    end
  end

  defp run_step({:status, name}, client, set) do
    with {:ok, _text} <- Client.status(client, name), do: {:ok, set}
  end

  defp run_step({:expect, name, matcher}, client, set),
    do: until_match(client, name, matcher, set.grace, set, :expect)

  defp run_step({:wait, name, matcher}, client, set),
    do: until_match(client, name, matcher, set.timeout, set, :wait)

  defp run_step({:download, _path, lines}, client, set) do
    with {:ok, command} <-
           transfer(client, set, fn -> Client.download_program(client, lines) end),
         :ok <- await_all(client, [command], set) do
      {:ok, set}
    end
  end

  defp run_step(:upload, client, set) do
    with {:ok, command, lines} <- transfer(client, set, fn -> Client.upload_program(client) end),
         :ok <- await_all(client, [command], set) do
      {:uploaded, lines}
    end
  end

  defp run_step({:timeout, ms}, _client, set), do: {:ok, %{set | timeout: ms}}

  # A program transfer that broke off on the link, or whose program arrived other than it was
  # sent (the CRC of the whole program: the CEC ended a download ERROR and kept its old NC file,
  # or the lines an upload brought are not the CEC's), is made again from the start, as a new
  # command, at most `transfer_retries` times. A transfer stores or sends a program and moves
  # nothing, so this re-runs nothing physical.
  defp transfer(client, set, fun, try \\ 1) do
    case fun.() do
      {:error, %ClientError{reason: reason} = error}
      when reason in [:transfer_failed, :program_crc] and try <= set.transfer_retries ->
        :ok = Client.note(client, "#{Exception.message(error)}: the transfer is made again")
        transfer(client, set, fun, try + 1)

      result ->
        result
    end
  end

  defp await_all(client, numbered, set) do
    Enum.reduce_while(numbered, :ok, fn {letter, number}, :ok ->
      case Client.await_command(client, letter, number, set.timeout, poll_interval: set.poll) do
        :done -> {:cont, :ok}
        {:error, _} = error -> {:halt, error}
      end
    end)
  end

  defp until_match(client, name, matcher, within, set, kind) do
    deadline = now() + within

    Stream.repeatedly(fn -> Client.status(client, name) end)
    |> Enum.reduce_while(nil, fn
      {:error, error}, _ ->
        {:halt, {:error, error}}

      {:ok, text}, _ ->
        cond do
          Script.matches?(matcher, text) ->
            {:halt, {:ok, set}}

          now() >= deadline ->
            {:halt, {:error, {kind, name, matcher, text, within}}}

          true ->
            Process.sleep(set.poll)
            {:cont, nil}
        end
    end)
  end

  defp reason(%ClientError{} = error), do: Exception.message(error)

  defp reason({:expect, name, matcher, text, _within}),
    do: "#{name} is #{inspect(text)}, expected #{Script.describe(matcher)}"

  defp reason({:wait, name, matcher, text, within}),
    do:
      "#{name} did not become #{Script.describe(matcher)} within #{within} ms; last #{inspect(text)}"

  defp now, do: System.monotonic_time(:millisecond)
end
