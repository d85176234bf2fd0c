defmodule Vws.Ops.Web.Tokens do
  @moduledoc """
  The dashboard's tokens (the control token and the read token, `Vws.Ops.Web`), from files or
  the environment — never from a command line, where every local user reads them (`ps`,
  `/proc/<pid>/cmdline`; issue 30 item 5).

  Where each is found, first match wins:

    1. the file given on the command line (`mix vws.serve --http-token-file PATH`,
       `--http-read-token-file PATH`);
    2. the file named in `VWS_HTTP_TOKEN_FILE` / `VWS_HTTP_READ_TOKEN_FILE`;
    3. the value of `VWS_HTTP_TOKEN` / `VWS_HTTP_READ_TOKEN` (a systemd unit's `EnvironmentFile`
       is such a place: the environment of a process is readable by its user and root only).

  A token file holds the token on its first line (surrounding whitespace and the newline are
  not part of it); it must not be empty, nor readable by every user (mode 0600, or 0640 for a
  group such as the service's).
  """

  import Bitwise

  @type result :: {:ok, String.t() | nil} | {:error, String.t()}

  @doc "The control token: from `file`, else `$VWS_HTTP_TOKEN_FILE`, else `$VWS_HTTP_TOKEN`, else nil."
  @spec control(Path.t() | nil) :: result
  def control(file \\ nil),
    do: resolve(file, "VWS_HTTP_TOKEN_FILE", "VWS_HTTP_TOKEN", "the control token")

  @doc "The read token: from `file`, else `$VWS_HTTP_READ_TOKEN_FILE`, else `$VWS_HTTP_READ_TOKEN`, else nil."
  @spec read(Path.t() | nil) :: result
  def read(file \\ nil),
    do: resolve(file, "VWS_HTTP_READ_TOKEN_FILE", "VWS_HTTP_READ_TOKEN", "the read token")

  defp resolve(file, file_var, var, what) do
    cond do
      file != nil -> read_file(file, what)
      path = env(file_var) -> read_file(path, "#{what} (#{file_var})")
      true -> {:ok, env(var)}
    end
  end

  @doc """
  The token in `path`; `what` names it in the error.

      iex> Vws.Ops.Web.Tokens.read_file("/no/such/file", "the control token")
      {:error, "cannot read the control token from /no/such/file: no such file or directory"}
  """
  @spec read_file(Path.t(), String.t()) :: result
  def read_file(path, what) do
    with {:ok, %File.Stat{type: :regular, mode: mode}} <- File.stat(path),
         :ok <- private(mode, path, what),
         {:ok, text} <- File.read(path) do
      case text |> String.split("\n", parts: 2) |> hd() |> String.trim() do
        "" -> {:error, "#{what} file #{path} is empty"}
        token -> {:ok, token}
      end
    else
      {:ok, %File.Stat{type: type}} ->
        {:error, "#{what} file #{path} is a #{type}, not a regular file"}

      {:error, message} when is_binary(message) ->
        {:error, message}

      {:error, reason} ->
        {:error, "cannot read #{what} from #{path}: #{:file.format_error(reason)}"}
    end
  end

  defp private(mode, path, what) do
    if (mode &&& 0o004) == 0,
      do: :ok,
      else: {:error, "#{what} file #{path} is readable by every user: chmod 0600 it"}
  end

  defp env(name) do
    case System.get_env(name) do
      nil -> nil
      value -> if String.trim(value) == "", do: nil, else: String.trim(value)
    end
  end
end
