defmodule Vws.Web.Handler do
  @moduledoc """
  The `:httpd` callback module of `Vws.Web`: routes each request to the dashboard page, the JSON
  state, the control action or the MTConnect agent, and writes the whole response itself.
  """
  require Record

  Record.defrecordp(:mod, Record.extract(:mod, from_lib: "inets/include/httpd.hrl"))

  alias Vws.MTConnect.Agent

  @token_header ~c"x-vws-token"

  @doc false
  # httpd's module callback (the name is a reserved word in Elixir)
  def unquote(:do)(request) do
    settings = :httpd_util.lookup(mod(request, :config_db), :vws_web)
    port = :httpd_util.lookup(mod(request, :config_db), :port)
    method = to_string(mod(request, :method))
    uri = URI.parse(to_string(mod(request, :request_uri)))
    query = decode_query(uri.query)
    segments = String.split(uri.path || "/", "/", trim: true)

    started = System.monotonic_time()

    {status, type, body} =
      try do
        route(method, segments, query, request, settings)
      rescue
        e -> {500, "text/plain", "internal error: " <> Exception.message(e)}
      catch
        :exit, reason -> {503, "text/plain", "not available: " <> inspect(reason, limit: 5)}
      end

    body = IO.iodata_to_binary(body)
    body = if method == "HEAD", do: "", else: body

    head = [
      code: status,
      content_type: String.to_charlist(type),
      content_length: String.to_charlist(Integer.to_string(byte_size(body))),
      cache_control: ~c"no-store"
    ]

    Vws.Telemetry.execute(
      [:vws, :web, :request],
      %{duration: System.monotonic_time() - started, bytes: byte_size(body)},
      %{method: method, path: uri.path, status: status, port: port}
    )

    {:proceed, [{:response, {:response, head, body}}]}
  end

  defp decode_query(nil), do: %{}

  defp decode_query(q) do
    URI.decode_query(q)
  rescue
    _ -> %{}
  end

  @read ["GET", "HEAD"]

  defp route(m, [], _q, _r, _s) when m in @read,
    do: {200, "text/html; charset=utf-8", Vws.Web.Page.html()}

  defp route(m, ["api", "state"], _q, _r, s) when m in @read,
    do: {200, "application/json", Vws.JSON.encode(Vws.Web.State.build(control: s.token != nil))}

  defp route("POST", ["api", "status"], q, r, s), do: control(q, r, s)

  defp route(m, [request], q, _r, s) when m in @read and request in ~w(probe current sample),
    do: mtconnect(request, nil, q, s)

  defp route(m, [device, request], q, _r, s)
       when m in @read and request in ~w(probe current sample) and device != "api",
       do: mtconnect(request, device, q, s)

  defp route(m, _path, _q, _r, _s) when m in @read, do: {404, "text/plain", "not found"}
  defp route(_m, _path, _q, _r, _s), do: {405, "text/plain", "method not allowed"}

  ## Control

  defp control(q, request, %{token: token}) do
    given = header(request, @token_header)

    cond do
      token == nil ->
        {403, "application/json",
         Vws.JSON.encode(%{error: "read-only: no control token configured"})}

      given == nil or not secure_equal?(given, token) ->
        {403, "application/json",
         Vws.JSON.encode(%{error: "control needs the right x-vws-token"})}

      true ->
        status_query(q)
    end
  end

  defp status_query(%{"ws" => ws, "name" => name}) do
    case Enum.find(Vws.Workstation.list(), &(Vws.Web.State.label(&1) == ws)) do
      nil ->
        {404, "application/json", Vws.JSON.encode(%{error: "no workstation #{ws}"})}

      id ->
        answer = Vws.Status.answer(id, name)
        {200, "application/json", Vws.JSON.encode(%{workstation: ws, name: name, answer: answer})}
    end
  end

  defp status_query(_q),
    do: {400, "application/json", Vws.JSON.encode(%{error: "needs ws and name"})}

  defp header(request, name) do
    case List.keyfind(mod(request, :parsed_header), name, 0) do
      {_, value} -> to_string(value)
      nil -> nil
    end
  end

  @doc false
  # Compares two strings in time that does not depend on where they differ.
  def secure_equal?(a, b) when byte_size(a) == byte_size(b) do
    Enum.reduce(Enum.zip(:binary.bin_to_list(a), :binary.bin_to_list(b)), 0, fn {x, y}, acc ->
      Bitwise.bor(acc, Bitwise.bxor(x, y))
    end) == 0
  end

  def secure_equal?(_a, _b), do: false

  ## MTConnect

  defp mtconnect(request, device, q, %{agent: agent}) do
    result =
      case request do
        "probe" ->
          Agent.probe(agent, device)

        "current" ->
          Agent.current(agent, device)

        "sample" ->
          with {:ok, from} <- integer(q, "from", agent),
               {:ok, count} <- integer(q, "count", agent) do
            Agent.sample(agent, from, count, device)
          end
      end

    case result do
      {:ok, xml} -> {200, "application/xml", xml}
      {:error, status, xml} -> {status, "application/xml", xml}
    end
  end

  defp integer(q, key, agent) do
    case Map.fetch(q, key) do
      :error ->
        {:ok, nil}

      {:ok, text} ->
        case Integer.parse(String.trim(text)) do
          {n, ""} ->
            {:ok, n}

          _ ->
            {:error, 400,
             Agent.error(agent, "INVALID_REQUEST", "'#{key}' must be an integer, not #{text}")}
        end
    end
  end
end
