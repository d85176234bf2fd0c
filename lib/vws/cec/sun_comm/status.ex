defmodule Vws.CEC.SunComm.Status do
  @moduledoc """
  SUN_COMM's Status subroutine (seed §2.3.6, Table 2, App. I G): the answer to a status command,
  read from the mailboxes alone — it never asks a partition, so it answers at once even while a
  partition is busy or restarting.

  Command-status names (`ROBOT_CMD`, `MONARCH_CMD`, `GRIPPER_CMD`, `FIXTURE_CMD` alias `VISE_CMD`,
  `VACUUM_CMD`, `HYDRAULIC_CMD`) answer `cccc` + `DONE` | `EXECUTING` | `ERROR <reason>` (`0000NONE`
  before any command). Device-status names (`GRIPPER`, `TABLE`, `VISE`, `TRAYS`, `VACUUM`,
  `TLI_TABLE`, `CHANGER_1`, `MONARCH`, `WHERE_ROBOT`, `PALLET`) answer the text of their
  device-status location, `NO DATA` before anything was written there. `<L>_CMD` for a set letter
  `L` the CEC does not know answers the error of the last command of that letter (`0000NONE`
  before any; PROTOCOLS.md §1 rule 5 — a command of an unknown set breaks a rule like the
  others). Anything else answers `ERROR UNKNOWN STATUS <name>`. Answers are cut to 94 characters (PROTOCOLS.md §1).
  """

  alias Vws.CEC.Mailbox

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

  @doc "Every status command name understood."
  @spec names() :: [String.t()]
  def names, do: Map.keys(@command_names) ++ @device_names

  @doc "The status text answering status command `name` for workstation `ws`."
  @spec answer(term, String.t()) :: String.t()
  def answer(ws, name) do
    name = name |> String.trim() |> String.upcase()

    text =
      cond do
        partition = @command_names[name] ->
          {number, status} = Mailbox.command_status(ws, partition)
          number_text(number) <> Mailbox.status_word(status)

        unknown_set_letter(name) ->
          {number, status} = Mailbox.unknown_status(ws, unknown_set_letter(name))
          number_text(number) <> Mailbox.status_word(status)

        name in @device_names ->
          case Mailbox.get_device(ws, Mailbox.device_location(name)) do
            {nil, _age} -> "NO DATA"
            {text, _age} when is_binary(text) -> text
            {other, _age} -> Mailbox.device_text(other)
          end

        true ->
          "ERROR UNKNOWN STATUS " <> name
      end

    String.slice(text, 0, @max_text)
  end

  # `Q_CMD` for a letter that names no command set
  defp unknown_set_letter(<<letter, "_CMD">>) when letter in ?A..?Z do
    case Vws.Codecs.WC.Command.set_for_letter(<<letter>>) do
      {:unknown, l} -> l
      _known -> nil
    end
  end

  defp unknown_set_letter(_name), do: nil

  defp number_text(nil), do: "0000"
  defp number_text(n), do: Vws.Codecs.WC.Command.pad4(n)
end
