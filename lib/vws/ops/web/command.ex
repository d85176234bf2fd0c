defmodule Vws.Ops.Web.Command do
  @moduledoc """
  The dashboard's control actions (`POST /api/command`, control token only): the few commands an
  operator needs between the WC's cycles, each run through SUN_COMM's own command path
  (`Vws.CEC.SunComm.local_command/4`: the Parser's rules, the journal, the partition's dispatch
  and its interlocks) exactly as a WC string's command — never around it.

  Only these, the text exactly as a WC sends it:

    * `M DOWNLOAD_GE(nnnnnn.PRO/v)` (or without `/v`: the latest) — a library version to the machine;
    * `M COMPARE_GE(nnnnnn.PRO)`, `M UPLOAD_GE(nnnnnn.PRO)`, `M DRIP_FEED`;
    * `M DRIP_FEED(nnnnnn.PRO)`, `M DRIP_FEED(nnnnnn.PRO/v)`, `M DRIP_FEED(nnnnnn.PRO/Nk)`,
      `M DRIP_FEED(nnnnnn.PRO/v/Nk)` — a library program drip-fed, restarted at line k
      (issue 27; the restored preamble is shown on the dashboard before it is sent);
    * `R RELEASE_TABLE`, `F RELEASE_TABLE`, `M RELEASE_TABLE`, `R RELEASE_TRAY1`, `R RELEASE_TRAY2` —
      a lease left held after a failed cycle.

  Each gets a command number of its own, 9000–9999 in turn (the dashboard's: a WC numbers its
  commands from 0001 up), so its status location says which it is; the history
  (`Vws.Ops.Web.History`) records each action, sent or refused.
  """

  alias Vws.Codecs.WC.Command, as: WCCommand

  @max_body 1_024
  @program ~S"\d{6}\.PRO"
  # (\A…\z, not ^…$: $ also matches before a final newline)
  @allowed [
    {"M", ~r/\ADOWNLOAD_GE\(#{@program}(\/\d{1,4})?\)\z/},
    {"M", ~r/\ACOMPARE_GE\(#{@program}\)\z/},
    {"M", ~r/\AUPLOAD_GE\(#{@program}\)\z/},
    {"M", ~r/\ADRIP_FEED\z/},
    {"M", ~r/\ADRIP_FEED\(#{@program}(\/\d{1,6})?(\/N\d{1,7})?\)\z/},
    {"M", ~r/\ARELEASE_TABLE\z/},
    {"R", ~r/\ARELEASE_TABLE\z/},
    {"R", ~r/\ARELEASE_TRAY[12]\z/},
    {"F", ~r/\ARELEASE_TABLE\z/}
  ]

  @doc "The largest request body taken, in bytes."
  def max_body, do: @max_body

  @doc "Whether `set`/`text` is one of the operator's commands."
  @spec allowed?(String.t(), String.t()) :: boolean
  def allowed?(set, text) when is_binary(set) and is_binary(text),
    do: Enum.any?(@allowed, fn {s, re} -> s == set and Regex.match?(re, text) end)

  def allowed?(_set, _text), do: false

  @doc """
  Runs a request's JSON body `{"workstation", "set", "text"}`: `{http_status, answer_map}` —
  200 `%{workstation, set, number, text, status}` when dispatched (the status as it stands),
  else 400/404/409/413 with `error`.
  """
  @spec run(binary) :: {pos_integer, map}
  def run(body) when byte_size(body) > @max_body,
    do: {413, %{error: "body larger than #{@max_body} bytes"}}

  def run(body) do
    with {:ok, %{"workstation" => ws_label, "set" => set, "text" => text}}
         when is_binary(ws_label) and is_binary(set) and is_binary(text) <- decode(body),
         text = String.trim(text),
         true <- allowed?(set, text) || {:refused, set, text},
         {:ok, ws} <- workstation(ws_label) do
      :ok = Vws.Ops.Web.History.watch(ws)
      number = next_number()

      case Vws.CEC.SunComm.local_command(ws, set, number, text) do
        :ok ->
          Vws.Ops.Web.History.record(
            ws,
            "OPERATOR",
            "#{set}#{WCCommand.pad4(number)} #{text} sent",
            "ok"
          )

          {200,
           %{
             workstation: ws_label,
             set: set,
             number: WCCommand.pad4(number),
             text: text,
             status: status(ws, set, number),
             # taken after the command was: a page state built before it (a poll already on
             # its way, the cached snapshot) is older, and the page does not follow it from there
             time: Vws.Ops.Web.State.time()
           }}

        {:error, words} ->
          Vws.Ops.Web.History.record(ws, "OPERATOR", "#{set} #{text} refused: #{words}", "error")
          {409, %{error: words}}
      end
    else
      {:refused, set, text} ->
        {400, %{error: "not an operator command: #{set} #{text}"}}

      {:error, :no_workstation, label} ->
        {404, %{error: "no workstation #{label}"}}

      _ ->
        {400, %{error: "needs a JSON object with workstation, set and text"}}
    end
  catch
    :exit, _ -> {409, %{error: "the workstation's SUN_COMM is not answering"}}
  end

  @doc false
  # A flat JSON object whose values are strings (all this takes): `{:ok, map}` or `:error`.
  def decode(body) do
    with "{" <> rest <- String.trim_leading(body),
         {:ok, map, rest} <- members(String.trim_leading(rest), %{}),
         "" <- String.trim(rest) do
      {:ok, map}
    else
      _ -> :error
    end
  end

  defp members("}" <> rest, acc) when acc == %{}, do: {:ok, acc, rest}

  defp members(text, acc) do
    with {:ok, key, rest} <- string(text),
         ":" <> rest <- String.trim_leading(rest),
         {:ok, value, rest} <- string(String.trim_leading(rest)) do
      acc = Map.put(acc, key, value)

      case String.trim_leading(rest) do
        "," <> more -> members(String.trim_leading(more), acc)
        "}" <> more -> {:ok, acc, more}
        _ -> :error
      end
    else
      _ -> :error
    end
  end

  defp string("\"" <> rest), do: chars(rest, [])
  defp string(_), do: :error

  defp chars("\"" <> rest, acc), do: {:ok, acc |> Enum.reverse() |> IO.iodata_to_binary(), rest}

  defp chars("\\u" <> <<hex::binary-size(4), rest::binary>>, acc) do
    case Integer.parse(hex, 16) do
      {c, ""} when c < 0xD800 or c > 0xDFFF -> chars(rest, [<<c::utf8>> | acc])
      _ -> :error
    end
  end

  defp chars("\\" <> <<c, rest::binary>>, acc) do
    case c do
      ?" -> chars(rest, ["\"" | acc])
      ?\\ -> chars(rest, ["\\" | acc])
      ?/ -> chars(rest, ["/" | acc])
      ?n -> chars(rest, ["\n" | acc])
      ?t -> chars(rest, ["\t" | acc])
      _ -> :error
    end
  end

  defp chars(<<c, rest::binary>>, acc) when c >= 0x20, do: chars(rest, [<<c>> | acc])
  defp chars(_, _acc), do: :error

  defp workstation(label) do
    case Enum.find(Vws.CEC.Workstation.list(), &(Vws.Ops.Web.State.label(&1) == label)) do
      nil -> {:error, :no_workstation, label}
      ws -> {:ok, ws}
    end
  end

  # the command's status location as it stands: "9001 EXECUTING", or that a newer command holds it
  defp status(ws, set, number) do
    partition = WCCommand.set_for_letter(set)

    case Vws.CEC.Mailbox.command_status(ws, partition) do
      {^number, status} -> Vws.CEC.Mailbox.status_word(status)
      _ -> "EXECUTING"
    end
  rescue
    _ -> "EXECUTING"
  end

  @first 9000
  @last 9999

  # 9000, 9001, … 9999, 9000: node-wide, so two pages never share a number
  defp next_number do
    key = {__MODULE__, :counter}

    ref =
      case :persistent_term.get(key, nil) do
        nil ->
          ref = :atomics.new(1, [])
          :persistent_term.put(key, ref)
          ref

        ref ->
          ref
      end

    @first + rem(:atomics.add_get(ref, 1, 1) - 1, @last - @first + 1)
  end
end
