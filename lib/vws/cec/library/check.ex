defmodule Vws.CEC.Library.Check do
  @moduledoc """
  Whether bytes are an NC program the library may keep and the links can carry
  (`Vws.CEC.Library.check_program/1`, which documents the answers): pure, on the bytes alone.
  """

  # what the library keeps (Vws.CEC.Library.max_bytes/0): the longest drip feed, not what the
  # GE-2000 stores (Vws.Links.DNC.Program.max_stored_bytes/0, checked where a program is stored)
  @max_bytes 64 * 1024 * 1024

  @doc "The largest program the library keeps: see `Vws.CEC.Library.max_bytes/0`."
  @spec max_bytes() :: pos_integer
  def max_bytes, do: @max_bytes

  @doc "See `Vws.CEC.Library.check_program/1`."
  @spec program(binary) :: :ok | {:error, {:not_a_program, term}}
  def program(bytes) when is_binary(bytes) do
    lines = Vws.Links.DNC.Program.from_text(bytes)

    cond do
      byte_size(bytes) > @max_bytes ->
        {:error, {:not_a_program, {:too_large, byte_size(bytes)}}}

      offset = binary_at(bytes) ->
        {:error, {:not_a_program, {:binary, offset}}}

      control = control_at(lines) ->
        {:error, {:not_a_program, control}}

      String.trim(List.first(lines, "")) != "%" ->
        {:error, {:not_a_program, :no_start}}

      not Vws.Links.DNC.Program.complete?(bytes) or length(lines) < 2 ->
        {:error, {:not_a_program, :no_end}}

      true ->
        program_number(lines)
    end
  end

  # a NUL byte, or bytes that are not UTF-8 text: the offset of the first
  defp binary_at(bytes) do
    case :binary.match(bytes, <<0>>) do
      {offset, _} ->
        offset

      :nomatch ->
        case :unicode.characters_to_binary(bytes) do
          {:error, good, _rest} -> byte_size(good)
          {:incomplete, good, _rest} -> byte_size(good)
          _ -> nil
        end
    end
  end

  # a control character but TAB, CR, LF (the X3.28 transmission controls among them, which
  # `Vws.Links.DNC.Program.sendable?/1` refuses on the DNC link): {:control, byte, line}
  defp control_at(lines) do
    lines
    |> Enum.with_index(1)
    |> Enum.find_value(fn {line, i} ->
      for(<<c <- line>>, c < 0x20 and c not in [?\t, ?\r], do: c)
      |> Enum.concat(for <<c <- line>>, c == 0x7F, do: c)
      |> case do
        [c | _] -> {:control, c, i}
        [] -> nil
      end
    end)
  end

  # the program number on the first line after the opening %, comments and blank lines skipped
  defp program_number([_percent | lines]) do
    first =
      Enum.find(lines, fn line ->
        String.replace(line, ~r/\([^)]*\)?/, "") |> String.trim() != ""
      end)

    stripped = first |> to_string() |> String.replace(~r/\([^)]*\)?/, "") |> String.trim()

    if String.match?(stripped, ~r/^[Oo:]\s*\d/) do
      case Vws.Links.DNC.Program.number([stripped]) do
        {:ok, _} -> :ok
        {:error, reason} -> {:error, {:not_a_program, reason}}
      end
    else
      {:error, {:not_a_program, :no_program_number}}
    end
  end
end
