defmodule Vws.Partitions.Monarch.Transfers do
  @moduledoc """
  The one home of MONARCH's transfer history (issue 27): every NC program that goes over the
  DNC link for MONARCH — `DOWNLOAD_GE` in its forms, `UPLOAD_GE`, `DRIP_FEED`, the read-back of
  `COMPARE_GE(nnnnnn.PRO)` and of `Vws.Partitions.Monarch.compare/2`, a program the operator
  sends from the machine, one the operator asks for from the machine's panel
  (`Vws.Partitions.Monarch.RemoteRequest`, through `carried/4`) — is recorded in the program library's history
  (`Vws.CEC.Library.record_transfer/2`, `Vws.CEC.Library.History`).

  MONARCH's requests all pass `carried/4` (`Vws.Partitions.Monarch`'s `request/5`): a request
  whose operation carries a program (`S`/`E` part program, `RNS` read) is measured — bytes,
  text blocks, duration, rate, the link's retries and MONARCH's own re-requests. Inside a
  command (`command/2`, which MONARCH's `execute/2` enters first) the records wait for the
  command's end and are written with its result: `DONE`, or the `ERROR` words the WC sees (a
  download whose directory check failed is recorded `ERROR PROGRAM VERIFY FAILED …`, not as the
  line's success). Outside a command (iex) a record is written at once with the transfer's own
  result. So a new transfer path is recorded without code of its own as long as its program goes
  through `request/5`.

  Who asked: `ctx.requester` when given (`Vws.Partitions.Monarch.compare/2` says `iex`; a path
  that is no WC command — a request from the machine's panel — names itself there); else the
  WC string that carried the command (`WC string 0042 M0007`, from the last string when it holds
  that command), else `WC M0007`; without either, `CEC`. A program sent from the machine:
  `machine panel`.

  Without a program library nothing is recorded (the history lives in the library). A record
  that cannot be written is logged as an error; the command's result stays what it was.
  """

  require Logger

  alias Vws.CEC.Library
  alias Vws.Links.DNC.Program

  @programs [:part_program, :download_execute]
  @scope {__MODULE__, :pending}

  @doc "True for a DNC operation that carries an NC program."
  @spec program?(atom) :: boolean
  def program?(operation), do: operation in @programs

  @doc """
  Runs a command (`fun`) with its transfers recorded at its end, with its result. Returns `fun`'s
  result.
  """
  @spec command(map, (() -> result)) :: result when result: var
  def command(ctx, fun) do
    Process.put(@scope, %{requester: requester(ctx), records: []})

    result =
      try do
        fun.()
      catch
        kind, reason ->
          flush(ctx, "ERROR CRASHED")
          :erlang.raise(kind, reason, __STACKTRACE__)
      end

    flush(ctx, result_words(result))
    result
  end

  @doc """
  Makes the request `fun` (`{:ok, blocks} | {:error, words}`) for DNC `command` with `blocks` to
  send, and records it when it carries a program (see the moduledoc).
  """
  @spec carried(map, Vws.Links.DNC.Frame.Command.t(), [binary], (() -> result)) :: result
        when result: var
  def carried(ctx, command, blocks, fun) do
    if program?(command.operation) do
      retries_before = link_retries(ctx)
      Process.put({__MODULE__, :again}, 0)
      began = DateTime.utc_now() |> DateTime.truncate(:millisecond) |> DateTime.to_iso8601()
      started = System.monotonic_time(:millisecond)
      result = fun.()
      ms = System.monotonic_time(:millisecond) - started
      again = Process.delete({__MODULE__, :again}) || 0
      retries = max(link_retries(ctx) - retries_before, 0) + again

      text =
        case {command.direction, result} do
          {:send, _} -> IO.iodata_to_binary(blocks)
          {:receive, {:ok, got}} -> IO.iodata_to_binary(got)
          _ -> ""
        end

      count =
        case {command.direction, result} do
          {:send, _} -> length(blocks)
          {:receive, {:ok, got}} -> length(got)
          _ -> 0
        end

      record = %{
        at: began,
        program: program_name(command.text, text),
        bytes: byte_size(text),
        blocks: count,
        duration_ms: ms,
        chars_per_s: if(ms > 0, do: div(byte_size(text) * 1000, ms), else: 0),
        retries: retries,
        operation: operation_text(command),
        direction: if(command.direction == :send, do: "to machine", else: "from machine"),
        command: Map.get(ctx, :text) || "",
        text: text
      }

      case Process.get(@scope) do
        %{records: records} = scope ->
          Process.put(@scope, %{scope | records: records ++ [record]})

        nil ->
          write(ctx, record, requester(ctx), transfer_result(result))
      end

      result
    else
      fun.()
    end
  end

  @doc "Counts a request MONARCH made again after the line broke it off (in `carried/4`)."
  @spec again() :: :ok
  def again do
    if n = Process.get({__MODULE__, :again}), do: Process.put({__MODULE__, :again}, n + 1)
    :ok
  end

  @doc "Adds `note` (words: what a compare found) to the last transfer of the command under way."
  @spec note(String.t()) :: :ok
  def note(note) do
    case Process.get(@scope) do
      %{records: [_ | _] = records} = scope ->
        {last, rest} = List.pop_at(records, -1)
        Process.put(@scope, %{scope | records: rest ++ [Map.put(last, :note, note)]})

      _ ->
        :ok
    end

    :ok
  end

  @doc """
  Records a program the operator sent from the machine (`Vws.Partitions.Monarch.received_program/5`):
  `result` `:ok` or `{:error, words}`.
  """
  @spec received(term, String.t(), binary, non_neg_integer, :ok | {:error, String.t()}) :: :ok
  def received(ws, name, text, blocks, result) do
    record = %{
      program: program_name(name, text),
      bytes: byte_size(text),
      blocks: blocks,
      operation: "part program",
      direction: "from machine",
      command: "SENT FROM THE MACHINE",
      text: text
    }

    write(%{workstation: ws}, record, "machine panel", transfer_result(result))
  end

  defp flush(ctx, result) do
    case Process.delete(@scope) do
      %{records: records, requester: requester} ->
        for r <- records, do: write(ctx, r, requester, result)

      nil ->
        :ok
    end

    :ok
  end

  defp write(ctx, record, requester, result) do
    ws = ctx.workstation

    if Library.enabled?(ws) do
      {text, record} = Map.pop(record, :text)
      {version, digest} = version_of(ws, record.program, text)

      fields =
        Map.merge(record, %{
          version: version,
          digest: digest,
          requester: Map.get(ctx, :requester) || requester,
          result: result
        })

      with {:error, reason} <- Library.record_transfer(ws, fields) do
        Logger.error(
          "MONARCH: transfer of #{record.program} not recorded in the history: #{inspect(reason)}"
        )
      end
    end

    :ok
  end

  # the library version holding exactly these bytes (nil when none does), and their digest
  defp version_of(_ws, _program, ""), do: {nil, nil}

  defp version_of(ws, program, text) do
    digest = Library.digest(text)

    with true <- is_binary(program),
         {:ok, versions} <- Library.versions(ws, program),
         {:ok, v} <- Library.same_as(versions, digest) do
      {v.version, String.slice(digest, 0, 16)}
    else
      _ -> {nil, String.slice(digest, 0, 16)}
    end
  end

  defp program_name(text, program) do
    case String.trim(to_string(text)) do
      "" ->
        case Program.file_name(program) do
          {:ok, name} -> name
          {:error, _} -> nil
        end

      name ->
        case Library.name(name) do
          {:ok, name} -> name
          {:error, _} -> name
        end
    end
  end

  defp operation_text(%{operation: :download_execute}), do: "drip feed"
  defp operation_text(%{operation: :part_program}), do: "part program"

  defp transfer_result({:ok, _}), do: "DONE"
  defp transfer_result(:ok), do: "DONE"
  defp transfer_result({:error, words}) when is_binary(words), do: "ERROR " <> words
  defp transfer_result(_), do: "ERROR"

  defp result_words(:done), do: "DONE"
  defp result_words(:ok), do: "DONE"
  defp result_words({:ok, _}), do: "DONE"
  defp result_words({:error, words}) when is_binary(words), do: "ERROR " <> words
  defp result_words(other), do: "ERROR " <> Vws.Codecs.WC.Words.of(other)

  # who asked: the caller's word (ctx.requester), else the WC string that carried the command,
  # when the last string holds it, else the CEC itself
  defp requester(%{requester: requester}) when is_binary(requester), do: requester

  defp requester(%{number: number} = ctx) when is_integer(number) do
    tag = "M" <> Vws.Codecs.WC.Command.pad4(number)

    case Vws.CEC.Mailbox.last_string(ctx.workstation) do
      {seq, line} when is_integer(seq) and is_binary(line) ->
        if String.contains?(line, "*" <> tag),
          do: "WC string #{Vws.Codecs.WC.Command.pad4(seq)} #{tag}",
          else: "WC #{tag}"

      _ ->
        "WC #{tag}"
    end
  rescue
    ArgumentError -> "WC"
  end

  defp requester(_ctx), do: "CEC"

  # Blocks sent again, NAKs sent, and ENQs beyond one bid a transmission (polls for a lost
  # reply, bids again): from the link's counters (Vws.Links.DNC.info/1), which a status read of
  # the monitor's between two of MONARCH's requests leaves even
  defp link_retries(ctx) do
    c = Vws.Links.DNC.info(ctx.link).counters

    Map.get(c, :retransmissions, 0) + Map.get(c, :naks_sent, 0) + Map.get(c, :enqs_sent, 0) -
      Map.get(c, :transmissions, 0)
  catch
    :exit, _ -> 0
  end
end
