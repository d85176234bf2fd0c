defmodule Vws.Codecs.WC.Status do
  @moduledoc """
  The status vocabulary of the WC link (seed §2.3.6, Table 2, App. I G; PROTOCOLS.md §1): the
  names a status command may ask and the words its answer is made of. The CEC answers from its
  mailboxes (`Vws.CEC.SunComm.Status`); the WC's scripts check the names they ask here.

    * Command-status names (`ROBOT_CMD`, `MONARCH_CMD`, `GRIPPER_CMD`, `FIXTURE_CMD` alias
      `VISE_CMD`, `VACUUM_CMD`, `HYDRAULIC_CMD`) answer `cccc` + `DONE` | `EXECUTING` |
      `ERROR <reason>` (`0000NONE` before any command; `NO DATA (why)` when a damaged journal
      could not tell).
    * Device-status names (`GRIPPER`, `TABLE`, `VISE`, `TRAYS`, `VACUUM`, `TLI_TABLE`,
      `CHANGER_1`, `MONARCH`, `WHERE_ROBOT`, `PALLET`) answer the text of their device-status
      location, `NO DATA` before anything was written there.
    * `<L>_CMD` for a set letter `L` the CEC does not know answers the error of the last command
      of that letter (PROTOCOLS.md §1 rule 5).
    * Anything else answers `ERROR UNKNOWN STATUS <name>`.

  An answer is cut to 94 characters, all a status reply can carry.

      iex> Vws.Codecs.WC.Status.classify("vise_cmd")
      {:command, :fixture}
      iex> Vws.Codecs.WC.Status.classify("Q_CMD")
      {:unknown_set, "Q"}
      iex> Vws.Codecs.WC.Status.command_answer(9, {:error, "NO LINK TO VAL II"})
      "0009ERROR NO LINK TO VAL II"
      iex> Vws.Codecs.WC.Status.command_answer(nil, :none)
      "0000NONE"
  """

  alias Vws.Codecs.WC.Command

  @max_text 94

  @command_names %{
    "ROBOT_CMD" => :robot,
    "MONARCH_CMD" => :monarch,
    "GRIPPER_CMD" => :gripper,
    "FIXTURE_CMD" => :fixture,
    "VISE_CMD" => :fixture,
    "VACUUM_CMD" => :vacuum,
    "HYDRAULIC_CMD" => :hydraulic
  }

  @device_names ~w(GRIPPER TABLE VISE TRAYS VACUUM TLI_TABLE CHANGER_1 MONARCH WHERE_ROBOT PALLET)

  @typedoc """
  A command status: `:none` (no command yet), `:executing`, `:done`, `{:error, reason}`, or
  `{:no_data, why}` (not known: a damaged journal could not restore it).
  """
  @type command_status ::
          :none | :executing | :done | {:error, String.t()} | {:no_data, String.t()}

  @doc "Every status command name understood."
  @spec names() :: [String.t()]
  def names, do: Map.keys(@command_names) ++ @device_names

  @doc """
  What a status name asks, upper-cased and trimmed first: `{:command, partition}`,
  `{:unknown_set, letter}`, `{:device, name}`, or `{:unknown, name}`.
  """
  @spec classify(String.t()) ::
          {:command, atom}
          | {:unknown_set, String.t()}
          | {:device, String.t()}
          | {:unknown, String.t()}
  # a name as the vocabulary spells it, as WCs send them: no trimming or Unicode upcasing
  def classify(name) when is_map_key(@command_names, name),
    do: {:command, Map.fetch!(@command_names, name)}

  def classify(name) when name in @device_names, do: {:device, name}

  def classify(name) do
    name = name |> String.trim() |> String.upcase()

    cond do
      partition = @command_names[name] -> {:command, partition}
      letter = unknown_set_letter(name) -> {:unknown_set, letter}
      name in @device_names -> {:device, name}
      true -> {:unknown, name}
    end
  end

  @doc "The answer to a command-status name: the command's number and its status word."
  @spec command_answer(0..9999 | nil, command_status) :: String.t()
  def command_answer(number, status), do: cut(number_text(number) <> word(status))

  @doc "The answer to a device-status name whose location holds `text` (nil: never written)."
  @spec device_answer(String.t() | nil) :: String.t()
  def device_answer(nil), do: "NO DATA"
  def device_answer(text) when is_binary(text), do: cut(text)

  @doc "The answer to a name that is none of the above."
  @spec unknown_answer(String.t()) :: String.t()
  def unknown_answer(name), do: cut("ERROR UNKNOWN STATUS " <> name)

  @doc """
  The status word of a command status as the WC reads it.

      iex> Vws.Codecs.WC.Status.word({:no_data, "JOURNAL DAMAGED"})
      "NO DATA (JOURNAL DAMAGED)"
  """
  @spec word(command_status) :: String.t()
  def word(:none), do: "NONE"
  def word(:executing), do: "EXECUTING"
  def word(:done), do: "DONE"
  def word({:error, reason}), do: "ERROR " <> reason
  def word({:no_data, why}), do: "NO DATA (" <> why <> ")"

  # `Q_CMD` for a letter that names no command set
  defp unknown_set_letter(<<letter, "_CMD">>) when letter in ?A..?Z do
    case Command.set_for_letter(<<letter>>) do
      {:unknown, l} -> l
      _known -> nil
    end
  end

  defp unknown_set_letter(_name), do: nil

  defp number_text(nil), do: "0000"
  defp number_text(n), do: Command.pad4(n)

  # no longer in bytes is no longer in characters: the slicing (which walks graphemes) only
  # for a text that may be too long — an answer is read at every status query
  defp cut(text) when byte_size(text) <= @max_text, do: text
  defp cut(text), do: String.slice(text, 0, @max_text)
end
