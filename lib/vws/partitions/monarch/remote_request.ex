defmodule Vws.Partitions.Monarch.RemoteRequest do
  @moduledoc """
  A remote request from the GE-2000's panel (ours, issue 27 item 1; docs/dnc-drip-feed.md
  "Remote request"): the operator asks for a program by number, and optionally version. The
  GE-2000 bids and sends the `R` command `RCS`/`RNS` + `nnnnnn.PRO` or `nnnnnn.PRO/v` — an
  `UPLOAD_GE` the other way round — and the CEC, master after its EOT, answers:

    * the library's latest released version, or version `v` if it is released
      (`Vws.Partitions.Monarch.released_program/3`), as text blocks: the machine files it as
      `nnnnnn.PRO`, whole or not at all, as any part program;
    * or one message block, `(MSG,REQUEST REFUSED <words>)` LF — not a program (no `%` line), so
      the machine files nothing and shows the words to the operator.

  It is the `DOWNLOAD_GE(nnnnnn.PRO[/v])` of the WC's set, asked from the machine: the request's
  text is read by that command's grammar (`Vws.Codecs.Commands`) and the interlock is decided by
  the one interlock table for that command (`Vws.CEC.Interlock.Rules.acquire/3`, MONARCH's
  rule for `DOWNLOAD_GE`). Every request is logged and told as telemetry
  `[:vws, :monarch, :remote_request]` (`bytes`; `workstation, program, version, result` —
  `:sent`, `:refused` with `reason`, or `:failed` when the answer could not be given — and
  `verified`). A program sent is then checked as after any `DOWNLOAD_GE`
  (`Vws.Partitions.Monarch.verify_download/5`: the status report without alarm, the directory
  entry's size and CRC-16 those of the bytes sent): `verified` is `:ok` or `{:error, words}`.
  The answer's transfer is the link's, with its progress and end like every other, and it is
  recorded in the transfer history through its one home (`Vws.Partitions.Monarch.Transfers`):
  requester `machine panel`, command `REQUESTED FROM THE MACHINE nnnnnn.PRO[/v]`, result `DONE`
  (sent and verified), the verify's `ERROR` words, or `ERROR REQUEST REFUSED <words>` (nothing
  sent: 0 bytes).

  Called by `Vws.Partitions.Monarch.Monitor` (the link's owner) within the link's
  `answer_timeout`. The owner does not wait for the check: its requests go over the same
  half-duplex link, and a request the machine makes meanwhile must find the owner free.
  """
  require Logger

  alias Vws.CEC.Interlock.Rules
  alias Vws.Links.DNC
  alias Vws.Links.DNC.Frame
  alias Vws.Partitions.Monarch
  alias Vws.Partitions.Monarch.Transfers

  @doc """
  Answers the GE-2000's `R` command `command` (announced as `{:request, ref, command, blocks}` by
  `link`) for workstation `ws`: the program, or the refusal's message. Returns what was told:
  `{:sent, file, version}`, `{:refused, words}` or `{:failed, reason}`, as soon as the answer is
  on its way; the transfer history's record, the check of a program sent and the log and
  telemetry follow in a process of their own.
  """
  @spec answer(term, DNC.link(), reference, Frame.Command.t(), keyword) ::
          {:sent, String.t(), pos_integer} | {:refused, String.t()} | {:failed, term}
  def answer(ws, link, ref, command, options \\ []) do
    asked = String.trim(command.text)
    {outcome, text} = program(ws, asked, options)
    blocks = Frame.split_text(text, DNC.max_text(link))

    outcome =
      case DNC.answer(link, ref, blocks) do
        :ok -> outcome
        {:error, reason} -> {:failed, reason}
      end

    # The history and the check after the answer wait for this very link (the check reads the
    # machine's report and directory over it), so they run in a process of their own: the owner
    # is then free to answer the machine's next R command. Waiting here, it left a request that
    # came during the check unanswered until the link's answer_timeout (alarm 7 on the machine).
    {:ok, _pid} =
      Task.start(fn -> record_and_check(ws, link, asked, outcome, text, blocks, options) end)

    outcome
  catch
    :exit, reason -> {:failed, reason}
  end

  # The transfer history's record through its one home, as MONARCH's own transfers: the program
  # sent (a refusal or a failure sends none), and its end — as after any DOWNLOAD_GE, the
  # machine's report and directory must say it holds the bytes; then the log and the telemetry.
  defp record_and_check(ws, link, asked, outcome, text, blocks, options) do
    history = %{
      workstation: ws,
      link: link,
      options: options,
      requester: "machine panel",
      text:
        String.trim(
          "REQUESTED FROM THE MACHINE " <>
            if(asked == "", do: "", else: Vws.Codecs.WC.Words.of(asked))
        )
    }

    {file, sent} =
      case outcome do
        {:sent, file, _v} -> {file, blocks}
        _ -> {asked |> String.split("/") |> hd(), []}
      end

    command = %Frame.Command{direction: :send, check: :crc, operation: :part_program, text: file}

    result =
      Transfers.carried(history, command, sent, fn -> ended(ws, link, outcome, text, options) end)

    verified =
      if match?({:sent, _, _}, outcome), do: if(result == {:ok, []}, do: :ok, else: result)

    tell(ws, asked, outcome, verified, byte_size(text))
  rescue
    # the history could not be written (its library gone with the workstation)
    error -> not_checked(asked, outcome, Exception.message(error))
  catch
    # the link or the workstation went away during the check
    :exit, reason -> not_checked(asked, outcome, inspect(reason, limit: 5))
  end

  defp not_checked(asked, outcome, why),
    do:
      Logger.warning(
        "MONARCH: the machine asked for #{asked}: #{inspect(outcome)}, not checked: #{why}"
      )

  defp ended(ws, link, {:sent, file, _v}, text, options) do
    with :ok <- Monarch.verify_download(ws, link, file, text, options), do: {:ok, []}
  end

  defp ended(_ws, _link, {:refused, words}, _text, _options),
    do: {:error, "REQUEST REFUSED " <> words}

  defp ended(_ws, _link, {:failed, _}, _text, _options), do: {:error, "NO ANSWER"}

  @doc """
  The refusal's message block for `words` (upper-case words and numbers). A comment ends at its
  first `)`, so the words' own parentheses are left out of it (`PROGRAM TOO LARGE 1020012 BYTES
  LIMIT 999999`); the log and the history keep the words whole.
  """
  @spec refusal(String.t()) :: String.t()
  def refusal(words), do: "(MSG,REQUEST REFUSED #{String.replace(words, ["(", ")"], "")})\n"

  defp program(ws, asked, options) do
    # the request's text read as DOWNLOAD_GE's argument: nnnnnn.PRO or nnnnnn.PRO/v
    with {:ok, {:download_ge, file, which} = download} <- parse(asked),
         {:ok, taken} <- interlock(ws, download, options) do
      result = Monarch.released_program(ws, file, which)
      ctx = ctx(ws, options)

      :ok =
        Rules.finish(
          download,
          taken,
          ctx,
          if(match?({:ok, _, _}, result), do: :done, else: result)
        )

      case result do
        {:ok, text, version} -> {{:sent, file, version}, text}
        {:error, words} -> {{:refused, words}, refusal(words)}
      end
    else
      {:error, words} -> {{:refused, words}, refusal(words)}
    end
  end

  defp parse(asked) do
    case Vws.Codecs.Commands.parse(:monarch, "DOWNLOAD_GE(#{asked})") do
      {:ok, {:download_ge, file, which}} when binary_part(file, 7, 3) == "PRO" ->
        {:ok, {:download_ge, file, which}}

      _ when asked == "" ->
        {:error, "NO PROGRAM NUMBER"}

      _ ->
        {:error, "BAD PROGRAM FILE #{Vws.Codecs.WC.Words.of(asked)}"}
    end
  end

  defp interlock(ws, download, options),
    do: Rules.acquire(Monarch, download, ctx(ws, options))

  defp ctx(ws, options), do: %{workstation: ws, partition: :monarch, options: options}

  defp tell(ws, asked, outcome, verified, bytes) do
    {program, version, result, reason} =
      case outcome do
        {:sent, file, v} -> {file, v, :sent, nil}
        {:refused, words} -> {asked, nil, :refused, words}
        {:failed, reason} -> {asked, nil, :failed, reason}
      end

    case outcome do
      {:sent, file, v} when verified == :ok ->
        Logger.info(
          "MONARCH: the machine asked for #{asked}: sent #{file} version #{v}, verified"
        )

      {:sent, file, v} ->
        {:error, words} = verified

        Logger.warning(
          "MONARCH: the machine asked for #{asked}: sent #{file} version #{v}, NOT verified: #{words}"
        )

      {:refused, words} ->
        Logger.warning("MONARCH: the machine asked for #{asked}: refused, #{words}")

      {:failed, reason} ->
        Logger.warning("MONARCH: the machine asked for #{asked}: no answer (#{inspect(reason)})")
    end

    Vws.Telemetry.execute([:vws, :monarch, :remote_request], %{bytes: bytes}, %{
      workstation: ws,
      program: program,
      version: version,
      result: result,
      reason: reason,
      verified: verified
    })
  end
end
