defmodule Vws.Web.Server do
  @moduledoc """
  Owns one `:inets` httpd instance: starts it in `init/1` (bound to the configured address and
  port), stops it when it terminates, and fails if httpd goes down so its supervisor restarts both.
  Requests are answered by `Vws.Web.Handler`, which finds this server's settings (agent, token)
  in the httpd configuration under `:vws_web`.
  """
  use GenServer
  require Logger

  @doc false
  def child_spec(opts), do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}}

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts), do: GenServer.start_link(__MODULE__, opts)

  @doc "The port httpd listens on."
  @spec port(pid) :: :inet.port_number()
  def port(server), do: GenServer.call(server, :port)

  @doc "The dashboard's URL."
  @spec url(pid) :: String.t()
  def url(server), do: GenServer.call(server, :url)

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)
    {:ok, _} = Application.ensure_all_started(:inets)
    bind = Keyword.get(opts, :bind, "127.0.0.1")

    {:ok, address} = :inet.parse_address(String.to_charlist(bind))

    root = Path.join(System.tmp_dir!(), "vws-httpd") |> String.to_charlist()
    File.mkdir_p!(to_string(root))

    settings = %{agent: Keyword.fetch!(opts, :agent), token: blank_to_nil(opts[:token])}

    config = [
      port: Keyword.get(opts, :port, 4000),
      bind_address: address,
      server_name: ~c"vws",
      server_root: root,
      document_root: root,
      modules: [Vws.Web.Handler],
      ipfamily: if(tuple_size(address) == 8, do: :inet6, else: :inet),
      max_clients: 50,
      keep_alive: true,
      vws_web: settings
    ]

    case :inets.start(:httpd, config) do
      {:ok, pid} ->
        ref = Process.monitor(pid)
        port = Keyword.fetch!(:httpd.info(pid, [:port]), :port)
        url = "http://#{host(bind)}:#{port}/"

        Logger.info(
          "VWS web server on #{url} (#{if settings.token, do: "control with token", else: "read-only"})"
        )

        {:ok, %{httpd: pid, monitor: ref, port: port, url: url}}

      {:error, reason} ->
        {:stop, {:cannot_listen, bind, opts[:port], reason}}
    end
  end

  defp host(bind) do
    if String.contains?(bind, ":"), do: "[#{bind}]", else: bind
  end

  defp blank_to_nil(nil), do: nil
  defp blank_to_nil(""), do: nil
  defp blank_to_nil(token) when is_binary(token), do: token

  @impl true
  def handle_call(:port, _from, s), do: {:reply, s.port, s}
  def handle_call(:url, _from, s), do: {:reply, s.url, s}

  @impl true
  def handle_info({:DOWN, ref, :process, _, reason}, %{monitor: ref} = s) do
    {:stop, {:httpd_down, reason}, %{s | httpd: nil}}
  end

  def handle_info(_msg, s), do: {:noreply, s}

  @impl true
  def terminate(_reason, %{httpd: pid}) when is_pid(pid) do
    :inets.stop(:httpd, pid)
    :ok
  end

  def terminate(_reason, _s), do: :ok
end
