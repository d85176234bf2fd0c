defmodule Vws.Peers.WC.Script do
  @moduledoc """
  Cycle scripts: what the workstation controller does, written as plain text a shop engineer can
  read and edit (files `priv/sims/*.vws`). `Vws.Peers.WC.Runner` runs them through a `Vws.Peers.WC.Client`.

  ## Format

  One step per line. Blank lines are ignored. `#` at the start of a line makes it a comment; so
  does ` # ` (a `#` with blanks around it) later in a line — a `#` glued to a word, as in
  `TRAY #1`, is text. Keywords and command letters may be written in either case.

  | step                               | what the WC does                                          |
  |------------------------------------|-----------------------------------------------------------|
  | `R DO MOVE SAFE`                   | sends one command (R robot, M Monarch, F vise, H hydraulic, G gripper, V vacuum) in a string, then polls its command status until it is `DONE` |
  | `R DO MOVE MV1 & G OPEN`           | several commands in one string (each set at most once), then polls each in turn |
  | `STATUS TRAYS`                     | asks a status once and logs the answer                     |
  | `EXPECT VISE VISE IS UNLOCKED`     | verifies a device: its status must begin with the text (upper case, blanks collapsed); asked again for a short grace, then the script stops |
  | `EXPECT GRIPPER ~ APART\\b`        | the same, with a regular expression after `~`             |
  | `WAIT MONARCH IDLE`                | polls a status until it begins with the text (or matches `~ regex`), for following a machining cycle |
  | `DOWNLOAD programs/001234.nc`      | `M DOWNLOAD_HP(cccc)` (the program's CRC) and the program's lines (path relative to the script), then polls the Monarch command |
  | `UPLOAD`                           | `M UPLOAD_SUN`, receives the program lines, then polls the Monarch command |
  | `TIMEOUT 90`                       | from here on, a command or a WAIT may take this many seconds |

  After every command the runner follows the seed's rule (§2.3.7): it asks the command's status
  (`ROBOT_CMD`, …) and repeats the question until the command's number appears; `DONE` lets the
  script go on, anything else stops it with the reason. The status queries are not written in
  the script: they follow each command by themselves.

      iex> {:ok, script} = Vws.Peers.WC.Script.parse(\"""
      ...> # seed Table 1, step 1
      ...> R DO MOVE MV1:TRANS(63.5,0,0,90,-90,0) & G OPEN
      ...> EXPECT TRAYS TRAY #1 IN POSITION   # glued '#' is text
      ...> \""")
      iex> Enum.map(script.steps, &{&1.line, &1.op})
      [{2, {:commands, [{"R", "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"}, {"G", "OPEN"}]}},
       {3, {:expect, "TRAYS", {:prefix, "TRAY #1 IN POSITION"}}}]
  """

  alias Vws.Codecs.WC.Command
  alias Vws.Peers.WC.ScriptError

  defmodule Step do
    @moduledoc "One step of a `Vws.Peers.WC.Script`: its line number, its text and what it does."
    @enforce_keys [:line, :source, :op]
    defstruct [:line, :source, :op]

    @type matcher :: {:prefix, String.t()} | {:regex, Regex.t()}
    @type op ::
            {:commands, [{String.t(), String.t()}, ...]}
            | {:status, String.t()}
            | {:expect, String.t(), matcher}
            | {:wait, String.t(), matcher}
            | {:download, Path.t(), [String.t()]}
            | :upload
            | {:timeout, pos_integer}

    @type t :: %__MODULE__{line: pos_integer, source: String.t(), op: op}
  end

  @enforce_keys [:steps]
  defstruct path: nil, steps: []

  @type t :: %__MODULE__{path: Path.t() | nil, steps: [Step.t(), ...]}

  @command_letters ~w(R M F H G V)
  @keywords ~w(STATUS EXPECT WAIT DOWNLOAD UPLOAD TIMEOUT)

  @doc "Reads and parses a script file; `DOWNLOAD` paths are relative to the file's directory."
  @spec parse_file(Path.t()) :: {:ok, t} | {:error, ScriptError.t()}
  def parse_file(path) do
    case File.read(path) do
      {:ok, text} -> parse(text, path: path, base_dir: Path.dirname(path))
      {:error, why} -> {:error, %ScriptError{reason: :unreadable, file: path, data: why}}
    end
  end

  @doc """
  Parses script text. Options: `:path` (named in errors), `:base_dir` (where `DOWNLOAD` paths
  start; the current directory by default). Returns the first error, with its line number.
  """
  @spec parse(String.t(), keyword) :: {:ok, t} | {:error, ScriptError.t()}
  def parse(text, opts \\ []) when is_binary(text) do
    path = opts[:path]
    base = Keyword.get_lazy(opts, :base_dir, &File.cwd!/0)

    text
    |> String.split("\n")
    |> Enum.with_index(1)
    |> Enum.reduce_while([], fn {raw, n}, steps ->
      source = raw |> strip_comment() |> String.trim()

      if source == "" do
        {:cont, steps}
      else
        case step(source, base) do
          {:ok, op} ->
            {:cont, [%Step{line: n, source: source, op: op} | steps]}

          {:error, reason, data} ->
            {:halt, {:error, %ScriptError{reason: reason, file: path, line: n, data: data}}}
        end
      end
    end)
    |> case do
      {:error, _} = error -> error
      [] -> {:error, %ScriptError{reason: :empty, file: path}}
      steps -> {:ok, %__MODULE__{path: path, steps: Enum.reverse(steps)}}
    end
  end

  @doc """
  Whether a status text satisfies an `EXPECT`/`WAIT` matcher: a prefix (compared in upper case
  with runs of blanks collapsed) or a regular expression.

      iex> Vws.Peers.WC.Script.matches?({:prefix, "VISE IS UNLOCKED"}, "VISE IS  UNLOCKED PART NOT IN VISE")
      true
      iex> Vws.Peers.WC.Script.matches?({:regex, ~r/\\d+ MM APART/}, "VISE JAWS ARE 12 MM APART")
      true
  """
  @spec matches?(Step.matcher(), String.t()) :: boolean
  def matches?({:prefix, prefix}, text), do: String.starts_with?(normalise(text), prefix)
  def matches?({:regex, regex}, text), do: Regex.match?(regex, text)

  @doc "A matcher as the script wrote it, for messages."
  @spec describe(Step.matcher()) :: String.t()
  def describe({:prefix, prefix}), do: inspect(prefix <> "…")
  def describe({:regex, regex}), do: "~ " <> Regex.source(regex)

  # A comment starts a line, or is a '#' with a blank (or the line's end) on each side.
  defp strip_comment(line) do
    line = String.trim_trailing(line, "\r")

    cond do
      String.starts_with?(String.trim_leading(line), "#") -> ""
      true -> line |> String.split(~r/\s#(\s|$)/, parts: 2) |> hd()
    end
  end

  defp step(source, base) do
    {word, rest} = split_word(source)
    keyword = String.upcase(word)

    cond do
      keyword in @keywords -> keyword_step(keyword, rest, base)
      byte_size(word) == 1 -> commands(source)
      true -> {:error, :unknown_step, source}
    end
  end

  defp split_word(text) do
    case String.split(text, ~r/\s+/, parts: 2) do
      [word, rest] -> {word, String.trim(rest)}
      [word] -> {word, ""}
    end
  end

  ## Commands

  defp commands(source) do
    source
    |> String.split("&")
    |> Enum.map(&String.trim/1)
    |> Enum.reduce_while({:ok, []}, fn part, {:ok, acc} ->
      case command(part) do
        {:ok, {letter, _} = c} ->
          if List.keymember?(acc, letter, 0),
            do: {:halt, {:error, :repeated_set, letter}},
            else: {:cont, {:ok, [c | acc]}}

        error ->
          {:halt, error}
      end
    end)
    |> case do
      {:ok, list} -> {:ok, {:commands, Enum.reverse(list)}}
      error -> error
    end
  end

  defp command(part) do
    {letter, text} = split_word(part)
    letter = String.upcase(letter)

    cond do
      letter not in @command_letters ->
        if byte_size(letter) == 1,
          do: {:error, :bad_command_set, letter},
          else: {:error, :unknown_step, part}

      text == "" ->
        {:error, :missing_argument, "#{letter} needs a command text"}

      true ->
        check_command(letter, text)
    end
  end

  defp check_command(letter, text) do
    set = Command.set_for_letter(letter)

    case Command.check(%Command{letter: letter, set: set, number: 1, text: text}) do
      {:error, _} ->
        {:error, :bad_command,
         {letter, text, "holds a '*' or a character the WC link cannot carry"}}

      :ok ->
        # DOWNLOAD_HP, DOWNLOAD_HP(cccc), UPLOAD_SUN: transfers, written DOWNLOAD and UPLOAD
        transfer = set == :monarch and Vws.Codecs.Commands.transfer(text) != nil

        case Vws.Codecs.Commands.parse(set, text) do
          _ when transfer ->
            {:error, :transfer_command, text}

          {:ok, _} ->
            {:ok, {letter, text}}

          {:error, :unknown} ->
            {:error, :bad_command, {letter, text, "not a command of the #{set_name(set)} set"}}

          {:error, why} ->
            {:error, :bad_command, {letter, text, why}}
        end
    end
  end

  defp set_name(:fixture), do: "vise"
  defp set_name(set), do: Atom.to_string(set)

  ## Keywords

  defp keyword_step("UPLOAD", "", _base), do: {:ok, :upload}

  defp keyword_step("UPLOAD", _rest, _base),
    do: {:error, :missing_argument, "UPLOAD takes nothing after it"}

  defp keyword_step("STATUS", rest, _base) do
    case split_word(rest) do
      {"", _} -> {:error, :missing_argument, "STATUS needs a status name"}
      {name, ""} -> with {:ok, name} <- status_name(name), do: {:ok, {:status, name}}
      _ -> {:error, :missing_argument, "STATUS takes one status name"}
    end
  end

  defp keyword_step(kind, rest, _base) when kind in ["EXPECT", "WAIT"] do
    op = if kind == "EXPECT", do: :expect, else: :wait

    with {name, text} when name != "" and text != "" <- split_word(rest),
         {:ok, name} <- status_name(name),
         {:ok, matcher} <- matcher(text) do
      {:ok, {op, name, matcher}}
    else
      {_, _} -> {:error, :missing_argument, "#{kind} needs a status name and the text to match"}
      error -> error
    end
  end

  defp keyword_step("DOWNLOAD", "", _base),
    do: {:error, :missing_argument, "DOWNLOAD needs the NC program's file"}

  defp keyword_step("DOWNLOAD", file, base) do
    path = Path.expand(file, base)

    with {:ok, text} <- read_program(path, file),
         lines = program_lines(text),
         :ok <- check_program(lines, file) do
      {:ok, {:download, path, lines}}
    end
  end

  defp keyword_step("TIMEOUT", text, _base) do
    case Float.parse(text) do
      {seconds, ""} when seconds > 0 -> {:ok, {:timeout, round(seconds * 1000)}}
      _ -> {:error, :bad_number, text}
    end
  end

  defp status_name(name) do
    name = String.upcase(name)

    if name in Vws.Codecs.WC.Status.names(),
      do: {:ok, name},
      else: {:error, :unknown_status, name}
  end

  defp matcher("~" <> pattern) do
    pattern = String.trim(pattern)

    cond do
      pattern == "" ->
        {:error, :missing_argument, "a pattern must follow ~"}

      true ->
        case Regex.compile(pattern) do
          {:ok, regex} -> {:ok, {:regex, regex}}
          {:error, {why, _at}} -> {:error, :bad_regex, {pattern, to_string(why)}}
        end
    end
  end

  defp matcher(text), do: {:ok, {:prefix, normalise(text)}}

  defp normalise(text), do: text |> String.upcase() |> String.split() |> Enum.join(" ")

  defp read_program(path, file) do
    case File.read(path) do
      {:ok, text} -> {:ok, text}
      {:error, why} -> {:error, :program_unreadable, {file, why}}
    end
  end

  defp program_lines(text) do
    text
    |> String.split("\n")
    |> Enum.map(&String.trim_trailing(&1, "\r"))
    |> Enum.reverse()
    |> Enum.drop_while(&(String.trim(&1) == ""))
    |> Enum.reverse()
  end

  defp check_program(lines, file) do
    case Vws.Peers.WC.Client.validate_program(lines) do
      :ok -> :ok
      {:error, why} -> {:error, :bad_program, {file, why}}
    end
  end
end
