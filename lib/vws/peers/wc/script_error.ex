defmodule Vws.Peers.WC.ScriptError do
  @moduledoc """
  Why a cycle script (`Vws.Peers.WC.Script`) could not be read. `file` is the script's path (or nil),
  `line` the script line at fault (or nil for the whole file), `data` the offending text.

  Reasons:

    * `:unreadable` — the script file could not be read; `data` is the `File` error.
    * `:empty` — the script has no step.
    * `:unknown_step` — the line starts with neither a command-set letter nor a keyword.
    * `:bad_command_set` — a command letter other than R, M, F, H, G, V (status queries are
      written `STATUS`, `EXPECT` or `WAIT`, acknowledgements are not sent from scripts).
    * `:repeated_set` — one string names a command set twice (seed §2.3.2 rule 1).
    * `:bad_command` — the text is not a command of its set (seed App. I), or holds a `*` or a
      character that cannot be sent.
    * `:transfer_command` — `M DOWNLOAD_HP` (with or without its CRC) or `M UPLOAD_SUN` written
      as a plain command: they carry program lines and are written `DOWNLOAD <file>` and
      `UPLOAD`.
    * `:unknown_status` — a status name SUN_COMM does not answer.
    * `:missing_argument` — a keyword without what it needs (a status name, a text, a file).
    * `:bad_regex` — the pattern after `~` does not compile.
    * `:bad_number` — `TIMEOUT` needs a positive number of seconds.
    * `:program_unreadable` — the NC program of a `DOWNLOAD` could not be read.
    * `:bad_program` — the NC program cannot be sent as DOWNLOAD_HP lines (see
      `Vws.Peers.WC.Client.validate_program/1`).

      iex> Exception.message(%Vws.Peers.WC.ScriptError{reason: :unknown_step, file: "cycle.vws", line: 7, data: "MOVE SAFE"})
      "cycle.vws:7: \\"MOVE SAFE\\" is not a step: a line starts with a command letter (R M F H G V) or STATUS, EXPECT, WAIT, DOWNLOAD, UPLOAD, TIMEOUT"
  """

  defexception [:reason, :file, :line, :data]

  @type reason ::
          :unreadable
          | :empty
          | :unknown_step
          | :bad_command_set
          | :repeated_set
          | :bad_command
          | :transfer_command
          | :unknown_status
          | :missing_argument
          | :bad_regex
          | :bad_number
          | :program_unreadable
          | :bad_program

  @type t :: %__MODULE__{
          reason: reason,
          file: Path.t() | nil,
          line: pos_integer | nil,
          data: term
        }

  @impl true
  def message(%__MODULE__{} = e), do: where(e) <> words(e)

  defp where(%{file: nil, line: nil}), do: ""
  defp where(%{file: nil, line: line}), do: "line #{line}: "
  defp where(%{file: file, line: nil}), do: "#{file}: "
  defp where(%{file: file, line: line}), do: "#{file}:#{line}: "

  defp words(%{reason: :unreadable, data: why}),
    do: "cannot read the script: #{:file.format_error(why)}"

  defp words(%{reason: :empty}), do: "the script has no step"

  defp words(%{reason: :unknown_step, data: text}) do
    "#{inspect(text)} is not a step: a line starts with a command letter (R M F H G V) or " <>
      "STATUS, EXPECT, WAIT, DOWNLOAD, UPLOAD, TIMEOUT"
  end

  defp words(%{reason: :bad_command_set, data: letter}) do
    "#{inspect(letter)} is not a command set a script sends: use R robot, M Monarch, F vise, " <>
      "H hydraulic, G gripper, V vacuum (status queries are STATUS, EXPECT, WAIT)"
  end

  defp words(%{reason: :repeated_set, data: letter}),
    do: "set #{letter} appears twice in one string; the CEC would refuse it (seed rule 1)"

  defp words(%{reason: :bad_command, data: {letter, text, why}}),
    do: "#{letter} #{text}: #{why}"

  defp words(%{reason: :transfer_command, data: text}) do
    "M #{text} moves program lines: write DOWNLOAD <file> or UPLOAD instead"
  end

  defp words(%{reason: :unknown_status, data: name}) do
    "#{inspect(name)} is not a status SUN_COMM answers; known: " <>
      Enum.join(Enum.sort(Vws.Codecs.WC.Status.names()), ", ")
  end

  defp words(%{reason: :missing_argument, data: what}), do: what

  defp words(%{reason: :bad_regex, data: {pattern, why}}),
    do: "the pattern #{inspect(pattern)} does not compile: #{why}"

  defp words(%{reason: :bad_number, data: text}),
    do: "TIMEOUT needs a positive number of seconds, got #{inspect(text)}"

  defp words(%{reason: :program_unreadable, data: {path, why}}),
    do: "cannot read the NC program #{path}: #{:file.format_error(why)}"

  defp words(%{reason: :bad_program, data: {path, why}}), do: "NC program #{path}: #{why}"

  defp words(%{reason: reason, data: data}), do: "#{inspect(reason)} #{inspect(data)}"
end
