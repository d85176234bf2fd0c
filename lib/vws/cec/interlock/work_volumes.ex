defmodule Vws.CEC.Interlock.WorkVolumes do
  @moduledoc """
  Which interlocked work volume each robot location lies in, and which volumes each robot
  program enters: `priv/work_volumes.exs` (see its comments), read by ROBOT before every motion.

      iex> wv = Vws.CEC.Interlock.WorkVolumes.load()
      iex> Vws.CEC.Interlock.WorkVolumes.location(wv, "VISE")
      {:ok, :table}
      iex> Vws.CEC.Interlock.WorkVolumes.location(wv, {:trans, "MV1", [63.5, 0.0, 0.0, 90.0, -90.0, 0.0]})
      {:ok, :tray1}
      iex> Vws.CEC.Interlock.WorkVolumes.location(wv, "MV9")
      {:error, "INTERLOCK NO WORK VOLUME FOR MV9"}
      iex> Vws.CEC.Interlock.WorkVolumes.program(wv, "DEBURR")
      {:ok, %{enters: [:table], ends: :safe}}
  """

  @type volume :: :safe | Vws.CEC.Interlock.volume()
  @type t :: %{
          locations: %{String.t() => volume},
          programs: %{String.t() => %{enters: [volume], ends: volume}},
          default: volume | nil
        }

  @doc "The path of the shipped file, `priv/work_volumes.exs`."
  @spec default_path() :: Path.t()
  def default_path, do: Path.join(:code.priv_dir(:vws), "work_volumes.exs")

  @doc """
  Loads and checks a work-volume map: from a file path, or a map in the file's shape (its
  location and program names are taken in capitals). Raises `ArgumentError` on a wrong shape.
  """
  @spec load(Path.t() | map) :: t
  def load(source \\ default_path())

  def load(path) when is_binary(path) do
    {raw, _binding} = Code.eval_file(path)
    load(raw)
  end

  def load(%{} = raw) do
    locations = Map.get(raw, :locations, %{})
    programs = Map.get(raw, :programs, %{})
    default = Map.get(raw, :default)

    unless is_map(locations) and Enum.all?(locations, &volume_entry?/1),
      do: raise(ArgumentError, "work volumes: locations must map names to volume atoms")

    unless is_map(programs) and Enum.all?(programs, &program_entry?/1),
      do: raise(ArgumentError, "work volumes: programs must map names to %{enters:, ends:}")

    unless default == nil or is_atom(default),
      do: raise(ArgumentError, "work volumes: default must be a volume atom or nil")

    %{
      locations: Map.new(locations, fn {name, v} -> {String.upcase(name), v} end),
      programs: Map.new(programs, fn {name, p} -> {String.upcase(name), p} end),
      default: default
    }
  end

  @doc "The shipped map, read once and kept (`:persistent_term`)."
  @spec default() :: t
  def default do
    case :persistent_term.get({__MODULE__, :default}, nil) do
      nil ->
        wv = load()
        :persistent_term.put({__MODULE__, :default}, wv)
        wv

      wv ->
        wv
    end
  end

  @doc """
  The volume of a location — a name or a compound `{:trans, name, values}`, which lies in the
  volume of its frame — or the error a command ends with when the location is not known.
  """
  @spec location(t, String.t() | {:trans, String.t(), list}) ::
          {:ok, volume} | {:error, String.t()}
  def location(wv, {:trans, name, _values}), do: location(wv, name)

  def location(wv, name) when is_binary(name) do
    case Map.get(wv.locations, String.upcase(name), wv.default) do
      nil -> {:error, "INTERLOCK NO WORK VOLUME FOR #{String.upcase(name)}"}
      volume -> {:ok, volume}
    end
  end

  @doc "The volumes a program enters and where it ends, or the error when it is not known."
  @spec program(t, String.t()) :: {:ok, %{enters: [volume], ends: volume}} | {:error, String.t()}
  def program(wv, name) do
    case Map.fetch(wv.programs, String.upcase(name)) do
      {:ok, p} -> {:ok, p}
      :error -> {:error, "INTERLOCK NO WORK VOLUME FOR PROGRAM #{String.upcase(name)}"}
    end
  end

  defp volume_entry?({name, v}), do: is_binary(name) and is_atom(v) and v != nil

  defp program_entry?({name, %{enters: enters, ends: ends}}),
    do: is_binary(name) and is_list(enters) and Enum.all?(enters, &is_atom/1) and is_atom(ends)

  defp program_entry?(_), do: false
end
