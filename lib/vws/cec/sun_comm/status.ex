defmodule Vws.CEC.SunComm.Status do
  @moduledoc """
  SUN_COMM's Status subroutine (seed §2.3.6): the answer to a status command, read from the
  mailboxes alone — it never asks a partition, so it answers at once even while a partition is
  busy or restarting. The names and the words of the answers are the WC link's vocabulary,
  `Vws.Codecs.WC.Status`.
  """

  alias Vws.CEC.Mailbox
  alias Vws.Codecs.WC.Status

  @doc "The status text answering status command `name` for workstation `ws`."
  @spec answer(term, String.t()) :: String.t()
  def answer(ws, name) do
    case Status.classify(name) do
      {:command, partition} ->
        {number, status} = Mailbox.command_status(ws, partition)
        Status.command_answer(number, status)

      {:unknown_set, letter} ->
        {number, status} = Mailbox.unknown_status(ws, letter)
        Status.command_answer(number, status)

      {:device, name} ->
        case Mailbox.get_device(ws, Mailbox.device_location(name)) do
          {text, _age} when is_binary(text) or text == nil -> Status.device_answer(text)
          {other, _age} -> Status.device_answer(Mailbox.device_text(other))
        end

      {:unknown, name} ->
        Status.unknown_answer(name)
    end
  end
end
