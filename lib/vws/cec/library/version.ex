defmodule Vws.CEC.Library.Version do
  @moduledoc """
  A version of a library program and what is known of versions from their names alone, pure:
  the SHA-256 digest that tells versions apart, released or from the machine, the latest
  released, the version holding given bytes, and where a machine's directory entry stands
  among them. `Vws.CEC.Library` documents each (`digest/1`, `released?/1`,
  `latest_released/1`, `same_as/2`, `on_machine/2`) and delegates here.
  """

  @typedoc "One stored version."
  @type t :: %{
          name: String.t(),
          version: pos_integer,
          at: DateTime.t(),
          source: String.t(),
          size: non_neg_integer,
          crc: 0..0xFFFF,
          digest: String.t() | nil,
          origin: :library | :machine,
          released: boolean,
          file: String.t()
        }

  @type on_machine ::
          :unknown
          | :unreadable
          | :absent
          | :differs
          | {:same, pos_integer}
          | {:ambiguous, [pos_integer]}

  # the source of a program the operator sent from the machine: its version is not released
  @from_machine "from the machine"

  @doc "The SHA-256 digest of `bytes`, 64 lower-case hexadecimal digits (`Vws.CEC.Library.digest/1`)."
  @spec digest(binary) :: String.t()
  def digest(bytes), do: :crypto.hash(:sha256, bytes) |> Base.encode16(case: :lower)

  @doc """
  Whether a version is released (`Vws.CEC.Library.released?/1`): its `released` field once the
  workflow's state is applied (`Vws.CEC.Library.Workflow`), else false only for one from the machine.
  """
  @spec released?(map) :: boolean
  def released?(%{released: released}) when is_boolean(released), do: released
  def released?(%{source: source}), do: source != @from_machine

  @doc "A version with its `origin` and `released` as its source says."
  @spec with_origin(map) :: t
  def with_origin(v) do
    released = released?(Map.delete(v, :released))
    Map.merge(v, %{origin: if(released, do: :library, else: :machine), released: released})
  end

  @doc "The newest released version among `versions`, oldest first (`Vws.CEC.Library.latest_released/1`)."
  @spec latest_released([t]) :: {:ok, t} | {:error, :not_released}
  def latest_released(versions) do
    case versions |> Enum.filter(&released?/1) |> List.last() do
      nil -> {:error, :not_released}
      v -> {:ok, v}
    end
  end

  @doc "The version holding the bytes of `digest` (`Vws.CEC.Library.same_as/2`)."
  @spec same_as([t], String.t() | nil) :: {:ok, t} | :none
  def same_as(_versions, nil), do: :none

  def same_as(versions, digest) do
    holding = Enum.filter(versions, &(&1.digest == digest))

    case Enum.filter(holding, &released?/1) do
      [] -> if holding == [], do: :none, else: {:ok, List.last(holding)}
      released -> {:ok, List.last(released)}
    end
  end

  @doc "Where the machine stands for one program (`Vws.CEC.Library.on_machine/2`)."
  @spec on_machine([map], map | nil | :unknown | :unreadable) :: on_machine
  def on_machine(_versions, :unknown), do: :unknown
  # its directory line could not be read: only reading the program back can tell
  def on_machine(_versions, :unreadable), do: :unreadable
  def on_machine(_versions, nil), do: :absent

  def on_machine(versions, %{size: size, crc: crc}) do
    case Enum.filter(versions, &(&1.size == size and &1.crc == crc)) do
      [] ->
        :differs

      matching ->
        case matching |> Enum.map(& &1.digest) |> Enum.uniq() do
          # one version stored before digests, whose bytes no longer match its name
          [nil] ->
            {:same, List.last(matching).version}

          [digest] ->
            {:ok, v} = same_as(matching, digest)
            {:same, v.version}

          _ ->
            {:ambiguous, Enum.map(matching, & &1.version)}
        end
    end
  end
end
