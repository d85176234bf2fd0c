defmodule Vws.Ops.DataDir do
  @moduledoc """
  Where the CEC keeps what must outlive it: one data directory per installation, everything in
  it per workstation id (decision, issue 15).

      $VWS_DATA_DIR                      default: $XDG_STATE_HOME/vws, else ~/.local/state/vws
      ├── journal/<workstation id>/      the command journal, the NC file and NC_UP (Vws.CEC.Journal)
      └── library/<workstation id>/      the program library, every version (Vws.CEC.Library)

  The program library is on wherever the journal is by default (`mix vws.serve`, `mix vws.demo`,
  the release), in `library/<id>` of the data directory; `VWS_LIBRARY_DIR` names it instead
  (`off`: none), and the mix tasks' `--library DIR` / `--no-library` come before both. `mix
  vws.library` finds it the same way, so it works on a running or a stopped workstation's library.

  The journal is on by default wherever the CEC runs — `mix vws.serve`, `mix vws.demo`, the
  release — in `journal/<id>` of the data directory. `VWS_JOURNAL_DIR` names the journal's
  directory itself instead (`off`: no journal); the mix tasks' `--journal DIR` and `--no-journal`
  come before both. A workstation id becomes one path segment: characters other than letters,
  digits, `-`, `_` and `.` are replaced by `_` (and an id of `.` or `..` is all `_`).

  One OS process at a time may use a journal directory (`Vws.CEC.Journal` keeps a `LOCK` file):
  two writing the same journal files would damage them. Two workstations on one host need two
  ids (or two directories).
  """

  @doc "The data directory: `$VWS_DATA_DIR`, else `$XDG_STATE_HOME/vws`, else `~/.local/state/vws`."
  @spec root() :: Path.t()
  def root do
    case env("VWS_DATA_DIR") do
      nil ->
        case env("XDG_STATE_HOME") do
          nil -> Path.join([System.user_home!(), ".local", "state", "vws"])
          state -> Path.join(state, "vws")
        end

      dir ->
        Path.expand(dir)
    end
  end

  @doc """
  The journal directory of workstation `id`, or nil for none. `choice` is what the user said:
  `{:dir, path}` (`--journal DIR`), `:off` (`--no-journal`) or `:default` (then
  `VWS_JOURNAL_DIR`, `off` meaning none, else `journal/<id>` under `root/0`).

      iex> Vws.Ops.DataDir.journal_dir("VWS", {:dir, "/tmp/j"})
      "/tmp/j"
      iex> Vws.Ops.DataDir.journal_dir("VWS", :off)
      nil
  """
  @spec journal_dir(String.t(), {:dir, Path.t()} | :off | :default) :: Path.t() | nil
  def journal_dir(_id, {:dir, dir}), do: Path.expand(dir)
  def journal_dir(_id, :off), do: nil

  def journal_dir(id, :default) do
    case env("VWS_JOURNAL_DIR") do
      nil -> Path.join([root(), "journal", segment(id)])
      "off" -> nil
      dir -> Path.expand(dir)
    end
  end

  @doc """
  The program library's directory of workstation `id` (`Vws.CEC.Library`), or nil for none:
  `{:dir, path}` (`--library DIR`), `:off` (`--no-library`) or `:default` (then
  `VWS_LIBRARY_DIR`, `off` meaning none, else `library/<id>` under `root/0`).

      iex> Vws.Ops.DataDir.library_dir("VWS", {:dir, "/tmp/l"})
      "/tmp/l"
      iex> Vws.Ops.DataDir.library_dir("../x", :default) |> Path.basename()
      ".._x"
  """
  @spec library_dir(String.t(), {:dir, Path.t()} | :off | :default) :: Path.t() | nil
  def library_dir(_id, {:dir, dir}), do: Path.expand(dir)
  def library_dir(_id, :off), do: nil

  def library_dir(id, :default) do
    case env("VWS_LIBRARY_DIR") do
      nil -> Path.join([root(), "library", segment(id)])
      "off" -> nil
      dir -> Path.expand(dir)
    end
  end

  @doc """
  The choice of the mix tasks' options `--library DIR` / `--no-library` (parsed as
  `library: :string, no_library: :boolean`).

      iex> Vws.Ops.DataDir.library_choice(no_library: true)
      :off
  """
  @spec library_choice(keyword) :: {:dir, Path.t()} | :off | :default
  def library_choice(opts) do
    cond do
      opts[:no_library] && opts[:library] -> raise ArgumentError, "--library and --no-library"
      opts[:no_library] -> :off
      is_binary(opts[:library]) -> {:dir, opts[:library]}
      true -> :default
    end
  end

  @doc """
  The choice of the mix tasks' options `--journal DIR` / `--no-journal` (parsed as
  `journal: :string, no_journal: :boolean`).

      iex> Vws.Ops.DataDir.choice(no_journal: true)
      :off
      iex> Vws.Ops.DataDir.choice(journal: "j")
      {:dir, "j"}
      iex> Vws.Ops.DataDir.choice([])
      :default
  """
  @spec choice(keyword) :: {:dir, Path.t()} | :off | :default
  def choice(opts) do
    cond do
      opts[:no_journal] && opts[:journal] -> raise ArgumentError, "--journal and --no-journal"
      opts[:no_journal] -> :off
      is_binary(opts[:journal]) -> {:dir, opts[:journal]}
      true -> :default
    end
  end

  defp segment(id) do
    case String.replace(to_string(id), ~r/[^A-Za-z0-9._-]/, "_") do
      dots when dots in ["", ".", ".."] -> String.duplicate("_", max(byte_size(dots), 1))
      segment -> segment
    end
  end

  defp env(name) do
    case System.get_env(name) do
      nil -> nil
      value -> if String.trim(value) == "", do: nil, else: String.trim(value)
    end
  end
end
