defmodule Vws.Ops.Health do
  @moduledoc """
  Is this node doing its job? The answer of `GET /health` (`Vws.Ops.Web`) and of the release's
  `bin/vws health`.

  A node is **healthy** when every workstation it was configured to run (a release's `VWS_WC`,
  the one `mix vws.serve` or `mix vws.demo` started: `expect/1`) runs, and each of its links is
  up — the WC link listening or connected, each device link connected — or has been down for
  no longer than `grace_ms` (default 15 s: three times the longest back-off wait of a link,
  5 s, `Vws.Links.Backoff`) while it dials again. Otherwise it is **failing**, with the reasons
  in words:

      VWS1 is not running
      VWS1: GE-2000 DNC link down for 42 s

  The answer leaks nothing of the dialogue with the WC or the equipment: `{"status":"ok"}`
  (HTTP 200), or `{"status":"failing","reasons":[…]}` (HTTP 503). `/health` needs no token —
  a probe (systemd, a load balancer, a monitoring system) has no secret —, but when the
  dashboard has a read token the reasons go only to a request carrying it; without it a
  failing node answers `{"status":"failing"}` alone.

  The link states come from `Vws.Ops.MTConnect.LinkWatch` (the links' telemetry, read again at
  each check), so a link's time down is counted from when it went down, not from the first
  probe that saw it.
  """

  use GenServer

  alias Vws.Ops.MTConnect.LinkWatch

  @default_grace_ms 15_000

  @link_names %{
    wc: "WC link",
    val: "VAL II link",
    dnc: "GE-2000 DNC link",
    daq1: "DAQ #1 link",
    hydraulic: "hydraulic controller link"
  }

  @doc false
  # Options: `:name` (default this module: the node's own), `:grace_ms`.
  def start_link(opts \\ []),
    do: GenServer.start_link(__MODULE__, opts, name: Keyword.get(opts, :name, __MODULE__))

  @doc false
  def child_spec(opts),
    do: %{id: Keyword.get(opts, :name, __MODULE__), start: {__MODULE__, :start_link, [opts]}}

  @doc "From now on the node is healthy only while workstation `id` runs with its links up."
  @spec expect(GenServer.server(), term) :: :ok
  def expect(server \\ __MODULE__, id), do: GenServer.call(server, {:expect, id})

  @doc "Workstation `id` is no longer expected (it was stopped on purpose)."
  @spec forget(GenServer.server(), term) :: :ok
  def forget(server \\ __MODULE__, id), do: GenServer.call(server, {:forget, id})

  @doc "The workstations this node is expected to run."
  @spec expected(GenServer.server()) :: [term]
  def expected(server \\ __MODULE__), do: GenServer.call(server, :expected)

  @doc "`:ok`, or `{:failing, reasons}` (lines of words)."
  @spec check(GenServer.server()) :: :ok | {:failing, [String.t()]}
  def check(server \\ __MODULE__) do
    GenServer.call(server, :check, 10_000)
  catch
    :exit, _ -> {:failing, ["the health check does not answer"]}
  end

  @doc """
  The HTTP answer: `{200, json}` or `{503, json}`; the reasons only if `reasons?`.
  """
  @spec answer(boolean, :ok | {:failing, [String.t()]}) :: {200 | 503, iodata}
  def answer(reasons?, result \\ check()) do
    case result do
      :ok ->
        {200, Vws.Ops.Web.JSON.encode(%{status: "ok"})}

      {:failing, reasons} ->
        body = if reasons?, do: %{status: "failing", reasons: reasons}, else: %{status: "failing"}
        {503, Vws.Ops.Web.JSON.encode(body)}
    end
  end

  ## The server

  @impl true
  def init(opts) do
    LinkWatch.attach()

    grace =
      Keyword.get(opts, :grace_ms) ||
        Keyword.get(Application.get_env(:vws, :health, []), :grace_ms, @default_grace_ms)

    {:ok, %{watch: LinkWatch.new(), expected: [], down: %{}, grace: grace}}
  end

  @impl true
  def handle_call({:expect, id}, _from, s) do
    s = if id in s.expected, do: s, else: %{s | expected: s.expected ++ [id]}
    {:reply, :ok, elem(read(s, id), 0)}
  end

  def handle_call({:forget, id}, _from, s) do
    down = Map.reject(s.down, fn {{ws, _key}, _} -> ws == id end)

    {:reply, :ok,
     %{
       s
       | expected: List.delete(s.expected, id),
         watch: LinkWatch.forget(s.watch, id),
         down: down
     }}
  end

  def handle_call(:expected, _from, s), do: {:reply, s.expected, s}

  def handle_call(:check, _from, s) do
    now = now()

    {s, reasons} =
      Enum.reduce(s.expected, {s, []}, fn id, {s, reasons} ->
        if running?(id) do
          {s, states} = read(s, id)

          down =
            for {key, "CLOSED"} <- Enum.sort(states),
                since = Map.get(s.down, {id, key}, now),
                now - since > s.grace,
                do: "#{label(id)}: #{link_name(key)} down for #{div(now - since, 1000)} s"

          {s, reasons ++ down}
        else
          {s, reasons ++ ["#{label(id)} is not running"]}
        end
      end)

    {:reply, if(reasons == [], do: :ok, else: {:failing, reasons}), s}
  end

  @impl true
  def handle_info({:link_event, pid, event, meta, at}, s) do
    case LinkWatch.event(s.watch, pid, event, meta, at) do
      {:change, id, key, state, _at} ->
        {:noreply, note(s, id, key, state)}

      {:read, id} ->
        if id in s.expected, do: {:noreply, elem(read(s, id), 0)}, else: {:noreply, s}

      :none ->
        {:noreply, s}
    end
  end

  def handle_info({:DOWN, _ref, :process, pid, _reason}, s) do
    case LinkWatch.down(s.watch, pid) do
      {watch, {:change, id, key, state, _at}} ->
        {:noreply, note(%{s | watch: watch}, id, key, state)}

      {watch, :none} ->
        {:noreply, %{s | watch: watch}}
    end
  end

  def handle_info(_other, s), do: {:noreply, s}

  # the links of `id` read now; each link's time down kept from when it was first seen down
  defp read(s, id) do
    {watch, states, _at} = LinkWatch.read(s.watch, id)

    s =
      Enum.reduce(states, %{s | watch: watch}, fn {key, state}, s -> note(s, id, key, state) end)

    {s, states}
  end

  defp note(s, id, key, "CLOSED"), do: %{s | down: Map.put_new(s.down, {id, key}, now())}
  defp note(s, id, key, _up), do: %{s | down: Map.delete(s.down, {id, key})}

  defp running?(id), do: is_pid(Vws.CEC.Workstation.whereis(id, :sun_comm))

  defp label(id) when is_binary(id), do: id
  defp label(id), do: inspect(id)

  defp link_name(key), do: Map.get(@link_names, key, "#{key} link")

  defp now, do: System.monotonic_time(:millisecond)

  ## bin/vws health

  @doc false
  # The release's `bin/vws health` (rel/overlays/bin/vws-health, through `bin/vws eval`): asks the
  # running node's /health over HTTP (VWS_HTTP_PORT, VWS_HTTP_BIND, the read token if set) and
  # halts with 0 (ok) or 1 (failing, or no node answering), having printed one line.
  def release_main do
    {status, line} = probe(System.get_env(), token_files: true)
    IO.puts(line)
    System.halt(status)
  end

  @doc false
  # `{exit_status, line}` for the environment `env` (a map of VWS_* variables); `token_files:
  # true` also reads the token files the node reads (VWS_HTTP_READ_TOKEN_FILE, …).
  def probe(env, opts \\ []) do
    get = fn name ->
      env |> Map.get(name, "") |> String.trim() |> then(&if(&1 == "", do: nil, else: &1))
    end

    # bin/vws-health keeps the node's port aside (VWS_HEALTH_HTTP_PORT) and turns its own off
    port =
      if Map.has_key?(env, "VWS_HEALTH_HTTP_PORT"),
        do: "VWS_HEALTH_HTTP_PORT",
        else: "VWS_HTTP_PORT"

    case get.(port) do
      "off" ->
        {1, "failing: VWS_HTTP_PORT is off; bin/vws health asks the node's HTTP server"}

      port ->
        port = port || "4000"

        host =
          case get.("VWS_HTTP_BIND") do
            nil -> "127.0.0.1"
            "0.0.0.0" -> "127.0.0.1"
            "::" -> "[::1]"
            other -> if String.contains?(other, ":"), do: "[#{other}]", else: other
          end

        http_probe("http://#{host}:#{port}/health", token(get, opts[:token_files]))
    end
  end

  # the read token (or the control token) to be told the reasons: given in `env`, else as the
  # node has them (Vws.Ops.Web.Tokens: VWS_HTTP_READ_TOKEN_FILE, …); none is no error — the
  # status is told without one
  defp token(get, files?) do
    get.("VWS_HTTP_READ_TOKEN") || get.("VWS_HTTP_TOKEN") ||
      if files? do
        Enum.find_value([&Vws.Ops.Web.Tokens.read/0, &Vws.Ops.Web.Tokens.control/0], fn f ->
          case f.() do
            {:ok, token} when is_binary(token) -> token
            _ -> nil
          end
        end)
      end
  end

  defp http_probe(url, token) do
    {:ok, _} = Application.ensure_all_started(:inets)
    headers = if token, do: [{~c"x-vws-token", String.to_charlist(token)}], else: []

    case :httpc.request(:get, {String.to_charlist(url), headers}, [timeout: 10_000],
           body_format: :binary
         ) do
      {:ok, {{_, 200, _}, _, _body}} ->
        {0, "ok"}

      {:ok, {{_, 503, _}, _, body}} ->
        reasons = Regex.scan(~r/"((?:[^"\\]|\\.)*)"/, body) |> Enum.map(&Enum.at(&1, 1))

        case Enum.drop_while(reasons, &(&1 != "reasons")) do
          ["reasons" | why] -> {1, "failing: " <> Enum.join(why, "; ")}
          _ -> {1, "failing"}
        end

      {:ok, {{_, status, _}, _, _}} ->
        {1, "failing: #{url} answered HTTP #{status}"}

      {:error, _reason} ->
        {1, "failing: no node answers at #{url}"}
    end
  end
end
