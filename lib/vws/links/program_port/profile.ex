defmodule Vws.Links.ProgramPort.Profile do
  @moduledoc """
  A DNC port's profile: what the control at its end speaks, and so which link serves it
  (`Vws.Links.ProgramPort`).

    * `ge2000-level2` — the GE-2000's DNC Level 2 (PROTOCOLS.md §2), `Vws.Links.DNC`; the default;
    * `rs232-xonxoff` — a plain RS-232 control: programs framed by `%` (leader, trailer, end of
      line, DC2/DC4 as the shop sets them) under XON/XOFF flow control, `Vws.Links.RS232`.

      iex> Vws.Links.ProgramPort.Profile.parse("rs232-xonxoff")
      {:ok, :rs232_xonxoff}
      iex> Vws.Links.ProgramPort.Profile.parse("fanuc-dnc2")
      {:error, ~s(unknown DNC port profile "fanuc-dnc2" (known: ge2000-level2, rs232-xonxoff))}
  """

  @type t :: :ge2000_level2 | :rs232_xonxoff

  @profiles [{"ge2000-level2", :ge2000_level2}, {"rs232-xonxoff", :rs232_xonxoff}]

  @doc "The profiles' names, as given on the command line."
  @spec names() :: [String.t()]
  def names, do: Enum.map(@profiles, &elem(&1, 0))

  @doc "A profile from its name (or the atom itself); an unknown one is said in words."
  @spec parse(String.t() | atom) :: {:ok, t} | {:error, String.t()}
  def parse(profile) when is_atom(profile) do
    if Enum.any?(@profiles, &(elem(&1, 1) == profile)),
      do: {:ok, profile},
      else: parse(Atom.to_string(profile))
  end

  def parse(name) when is_binary(name) do
    case List.keyfind(@profiles, name, 0) do
      {_, profile} ->
        {:ok, profile}

      nil ->
        shown = if String.printable?(name), do: String.slice(name, 0, 40), else: "(unprintable)"

        {:error,
         "unknown DNC port profile #{inspect(shown)} (known: #{Enum.join(names(), ", ")})"}
    end
  end

  def parse(other), do: {:error, "a DNC port profile is a name, not #{inspect(other, limit: 3)}"}

  @doc "The link module that serves a profile."
  @spec link_module(t) :: module
  def link_module(:ge2000_level2), do: Vws.Links.DNC
  def link_module(:rs232_xonxoff), do: Vws.Links.RS232
end
