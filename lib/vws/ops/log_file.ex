defmodule Vws.Ops.LogFile do
  @moduledoc """
  The node's log in files as well as on the console: an OTP `:logger_std_h` handler writing
  `vws-<ID>.log` in a directory — named after the node's workstation (`VWS_ID`, default `VWS`:
  `vws-VWS.log`), so that two releases logging to one directory (`/var/log/vws`) each keep
  their own file —, rotated by size: when it reaches `:max_bytes` (default 10 MB) it becomes
  `vws-<ID>.log.0` (the older ones `.1` …), and at most `:files` (default 10) old files are
  kept. Each line: time, workstation and partition when known, level, message.

  `Vws.Application` installs it from `config :vws, :log_file, dir: …` — in a release and for
  `mix vws.serve`, from `VWS_LOG_DIR` (see `config/runtime.exs`; a release without it writes
  to its own `log/` directory, `VWS_LOG_DIR=off` to the console only). The level is the
  logger's (`info` in a release, `VWS_LOG_LEVEL` to change it).
  """

  require Logger

  @handler :vws_file

  @doc """
  Adds the file handler (`:dir` required; `:workstation` — the id the file is named after,
  default `VWS`; `:max_bytes`, `:files`, `:id` — the handler id, default `:vws_file`). Returns
  `{:ok, path}` or `{:error, reason}` (the directory cannot be created or written: the console
  log goes on).
  """
  @spec start(keyword) :: {:ok, Path.t()} | {:error, term}
  def start(opts) do
    dir = Keyword.fetch!(opts, :dir)
    path = Path.join(dir, file_name(Keyword.get(opts, :workstation, "VWS")))

    config = %{
      # what the console leaves out too: supervisor progress and SASL reports (Elixir's Logger
      # drops them unless :handle_sasl_reports); crashes are logged as errors either way
      filter_default: :log,
      filters: [
        progress: {&:logger_filters.progress/2, :stop},
        sasl: {&:logger_filters.domain/2, {:stop, :sub, [:otp, :sasl]}}
      ],
      config: %{
        file: String.to_charlist(path),
        max_no_bytes: Keyword.get(opts, :max_bytes, 10_000_000),
        max_no_files: Keyword.get(opts, :files, 10),
        filesync_repeat_interval: 1_000
      },
      formatter:
        {__MODULE__,
         %{
           single_line: false,
           template: [
             :time,
             " ",
             {:workstation, ["workstation=", :workstation, " "], []},
             {:partition, ["partition=", :partition, " "], []},
             "[",
             :level,
             "] ",
             :msg,
             "\n"
           ]
         }}
    }

    with :ok <- File.mkdir_p(dir),
         :ok <- :logger.add_handler(Keyword.get(opts, :id, @handler), :logger_std_h, config) do
      {:ok, path}
    end
  end

  @doc """
  The log file's name for workstation `id`: `vws-<id>.log`, any character that does not belong
  in a file name made `_`.

      iex> Vws.Ops.LogFile.file_name("VWS1")
      "vws-VWS1.log"
      iex> Vws.Ops.LogFile.file_name("cell/A 2")
      "vws-cell_A_2.log"
  """
  @spec file_name(term) :: String.t()
  def file_name(id),
    do: "vws-" <> String.replace(to_string(id), ~r/[^A-Za-z0-9_.-]/, "_") <> ".log"

  @doc false
  # The formatter: :logger_formatter's, with the workstation id (a string, or any term) written
  # as text, not as an Erlang binary (<<"VWS">>).
  def format(%{meta: meta} = event, config) do
    meta =
      Enum.reduce([:workstation, :partition], meta, fn key, meta ->
        case meta do
          %{^key => value} when is_binary(value) -> %{meta | key => String.to_charlist(value)}
          %{^key => value} when is_atom(value) -> meta
          %{^key => value} -> %{meta | key => ~c"#{inspect(value)}"}
          _ -> meta
        end
      end)

    :logger_formatter.format(%{event | meta: meta}, config)
  end

  @doc false
  def check_config(config), do: :logger_formatter.check_config(config)

  @doc "Removes the file handler (`id`, default `:vws_file`), if it is there."
  @spec stop(atom) :: :ok
  def stop(id \\ @handler) do
    _ = :logger.remove_handler(id)
    :ok
  end

  @doc false
  # From the application's start: the configured file, if any; a failure is logged, not fatal.
  def start_configured do
    case Application.get_env(:vws, :log_file) do
      nil ->
        :ok

      opts ->
        # the file named after this node's workstation (a release's VWS_ID)
        id =
          get_in(Application.get_env(:vws, :workstation, []), [:id]) ||
            System.get_env("VWS_ID") || "VWS"

        case start(Keyword.put_new(opts, :workstation, id)) do
          {:ok, path} ->
            Logger.info("logging to #{path} as well as the console")

          {:error, reason} ->
            Logger.error(
              "cannot log to #{opts[:dir]}: #{inspect(reason)}; logging to the console only"
            )
        end
    end
  end
end
