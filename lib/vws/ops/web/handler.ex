defmodule Vws.Ops.Web.Handler do
  @moduledoc """
  The routes of `Vws.Ops.Web`: the dashboard page, the JSON state, the control action and the
  MTConnect agent. `Vws.Ops.Web.Server` reads a request's head, asks `authorize/2` whether it may go
  on — before a byte of its body is read — and then `handle/2` for the answer.

  A request is a map: `method` ("GET"…), `path`, `query` (decoded map), `headers` (lower-case
  names → values), and `body` for `handle/2`. An answer is `{status, content_type, body}` or
  `{status, content_type, body, extra_headers}`.

  ## Tokens

    * the **control token** (`:token`): `POST /api/status` and `POST /api/command`
      (`Vws.Ops.Web.Command`) need it in the `x-vws-token` header;
      without a control token configured every control request is refused 403;
    * the **read token** (`:read_token`, optional): when set, every other path needs it (or the
      control token) — as the password of HTTP Basic authentication (any user name; a browser
      asks once and sends it with the page's own requests) or in the `x-vws-token` header;
      otherwise 401. Without one the reads are open to whoever reaches the port.
    * `GET /health` (`Vws.Ops.Health`) needs neither: a probe has no secret. It says only
      `{"status":"ok"}` or `{"status":"failing"}`, and why it fails only with the read token
      (when one is set).
  """

  alias Vws.Ops.MTConnect.Agent

  @control ["api", "status"]
  @command ["api", "command"]

  @doc """
  Whether a request may go on, judged on its head alone: `:ok`, or `{:deny, answer}` (401 for a
  read without the read token, 403 for control without the control token).
  """
  @spec authorize(map, map) :: :ok | {:deny, tuple}
  def authorize(%{method: method, path: path, headers: headers}, settings) do
    cond do
      method == "POST" and segments(path) in [@control, @command] ->
        authorize_control(headers, settings)

      # a health probe has no secret: /health is open, and says the reasons only to a reader
      method in ["GET", "HEAD"] and segments(path) == ["health"] ->
        :ok

      true ->
        authorize_read(headers, settings)
    end
  end

  defp authorize_control(headers, %{token: token}) do
    given = headers["x-vws-token"]

    cond do
      token == nil ->
        {:deny,
         {403, "application/json",
          Vws.Ops.Web.JSON.encode(%{error: "read-only: no control token configured"})}}

      given == nil or not secure_equal?(given, token) ->
        {:deny,
         {403, "application/json",
          Vws.Ops.Web.JSON.encode(%{error: "control needs the right x-vws-token"})}}

      true ->
        :ok
    end
  end

  defp authorize_read(_headers, %{read_token: nil}), do: :ok

  defp authorize_read(headers, %{read_token: read, token: control}) do
    given = [headers["x-vws-token"], basic_password(headers["authorization"])]

    if Enum.any?(given, fn g ->
         g != nil and (secure_equal?(g, read) or secure_equal?(g, control))
       end) do
      :ok
    else
      {:deny,
       {401, "text/plain", "this server needs its read token",
        [{"www-authenticate", ~s(Basic realm="VWS", charset="UTF-8")}]}}
    end
  end

  defp basic_password("Basic " <> encoded) do
    with {:ok, decoded} <- Base.decode64(String.trim(encoded)),
         [_user, password] <- String.split(decoded, ":", parts: 2) do
      password
    else
      _ -> nil
    end
  end

  defp basic_password(_), do: nil

  @doc "The answer to an authorized request."
  @spec handle(map, map) :: tuple
  def handle(%{method: method, path: path, query: query} = request, settings) do
    try do
      route(method, segments(path), query, request, settings)
    rescue
      e -> {500, "text/plain", "internal error: " <> Exception.message(e)}
    catch
      :exit, reason -> {503, "text/plain", "not available: " <> inspect(reason, limit: 5)}
    end
  end

  defp segments(path), do: String.split(path, "/", trim: true)

  @read ["GET", "HEAD"]
  @mtconnect ~w(probe current sample assets)
  # A stream's `interval` and `heartbeat` (ms) at most 10 s — the standard's default heartbeat —
  # where the reference agent takes any C int: a stream then says something at least every 10 s
  # (plus `interval`), and an interval of 24.8 days cannot hold a connection silent. Beyond it the
  # request is refused OUT_OF_RANGE, as the reference agent refuses what is beyond its range.
  @max_ms 10_000

  defp route(m, [], _q, _r, _s) when m in @read,
    do: {200, "text/html; charset=utf-8", Vws.Ops.Web.Page.html()}

  defp route(m, ["api", "state"], _q, _r, s) when m in @read,
    do: state(s)

  # Vws.Ops.Health: 200 {"status":"ok"} or 503 with the reasons (with the read token, if one is set)
  defp route(m, ["health"], _q, r, s) when m in @read do
    {status, body} = Vws.Ops.Health.answer(authorize_read(r.headers, s) == :ok)
    {status, "application/json", body}
  end

  defp route("POST", @control, q, _r, _s), do: status_query(q)

  # an operator's command through SUN_COMM's command path (Vws.Ops.Web.Command)
  defp route("POST", @command, _q, r, _s) do
    {status, answer} = Vws.Ops.Web.Command.run(Map.get(r, :body) || "")
    {status, "application/json", Vws.Ops.Web.JSON.encode(answer)}
  end

  defp route(m, [request], q, r, s) when m in @read and request in @mtconnect,
    do: mtconnect(request, nil, q, r, s)

  defp route(m, [device, request], q, r, s)
       when m in @read and request in @mtconnect and device != "api",
       do: mtconnect(request, device, q, r, s)

  # any other path: the MTConnect agent's INVALID_URI, as the reference agent answers it
  defp route(m, path, _q, r, s) when m in @read and path != ["api", "state"] and path != [] do
    mtc_error(s, format(r, %{}), 404, "INVALID_URI", "no such request: #{r.path}")
  end

  defp route(m, _path, _q, _r, _s) when m in @read, do: {404, "text/plain", "not found"}
  defp route(_m, _path, _q, _r, _s), do: {405, "text/plain", "method not allowed"}

  defp state(s) do
    case Vws.Ops.Web.Snapshot.json(s.snapshot) do
      {:ok, json} -> {200, "application/json", json}
      {:error, why} -> {503, "application/json", Vws.Ops.Web.JSON.encode(%{error: why})}
    end
  end

  ## Control (authorized by authorize/2)

  defp status_query(%{"ws" => ws, "name" => name}) do
    case Enum.find(Vws.CEC.Workstation.list(), &(Vws.Ops.Web.State.label(&1) == ws)) do
      nil ->
        {404, "application/json", Vws.Ops.Web.JSON.encode(%{error: "no workstation #{ws}"})}

      id ->
        answer = Vws.CEC.SunComm.Status.answer(id, name)

        {200, "application/json",
         Vws.Ops.Web.JSON.encode(%{workstation: ws, name: name, answer: answer})}
    end
  end

  defp status_query(_q),
    do: {400, "application/json", Vws.Ops.Web.JSON.encode(%{error: "needs ws and name"})}

  @doc false
  # Compares two strings in time that does not depend on where they differ.
  def secure_equal?(a, b) when byte_size(a) == byte_size(b) do
    Enum.reduce(Enum.zip(:binary.bin_to_list(a), :binary.bin_to_list(b)), 0, fn {x, y}, acc ->
      Bitwise.bor(acc, Bitwise.bxor(x, y))
    end) == 0
  end

  def secure_equal?(_a, _b), do: false

  ## MTConnect
  #
  # The parameters of each request (as the reference agent knows them). A parameter that is not
  # one of them, a value of the wrong kind, or two that cannot go together is answered with an
  # MTConnectError document — never with data that ignores it (docs/mtconnect.md).

  @params %{
    "probe" => ~w(format),
    "current" => ~w(path at interval format),
    "sample" => ~w(path from count to interval heartbeat format),
    "assets" => ~w(type count removed device format)
  }

  defp mtconnect(_request, _device, :invalid, r, s),
    do: mtc_error(s, format(r, %{}), 400, "INVALID_REQUEST", "the query cannot be decoded")

  defp mtconnect(request, device, q, r, %{agent: agent} = s) do
    fmt = format(r, q)

    with :ok <- known_params(request, q),
         {:ok, fmt} <- fmt,
         {:ok, p} <- params(q) do
      p = Map.merge(p, %{device: device || p[:device], format: fmt})

      case run(request, agent, p) do
        {:ok, doc} ->
          {200, mime(fmt), doc}

        {:stream, first, more} ->
          {:stream, mime(fmt), first, more}

        {:error, status, doc} ->
          {status, mime(fmt), doc}
      end
    else
      {:bad, code, text} ->
        fmt = with({:ok, f} <- fmt, do: f, else: (_ -> :xml))
        mtc_error(s, {:ok, fmt}, 400, code, text)
    end
  end

  defp run("probe", agent, p), do: Agent.probe(agent, p.device, format: p.format)

  defp run("assets", agent, p),
    do: Agent.assets(agent, format: p.format, device: p.device, count: p[:count])

  defp run("current", agent, p) do
    cond do
      p[:interval] != nil and p[:at] != nil ->
        bad(agent, p, "INVALID_REQUEST", "'at' and 'interval' cannot be given together")

      p[:interval] != nil and (p.interval < 0 or p.interval > @max_ms) ->
        range(agent, p, "interval", p.interval)

      p[:interval] != nil ->
        stream(Vws.Ops.MTConnect.Stream.current(agent, p))

      true ->
        Agent.current(agent, p.device, at: p[:at], path: p[:path], format: p.format)
    end
  end

  defp run("sample", agent, p) do
    cond do
      p[:interval] != nil and p[:to] != nil ->
        bad(agent, p, "INVALID_REQUEST", "'to' and 'interval' cannot be given together")

      p[:interval] != nil and (p.interval < 0 or p.interval > @max_ms) ->
        range(agent, p, "interval", p.interval)

      p[:heartbeat] != nil and (p.heartbeat < 1 or p.heartbeat > @max_ms) ->
        range(agent, p, "heartbeat", p.heartbeat)

      p[:interval] != nil ->
        p = Map.merge(%{heartbeat: 10_000}, p, fn _k, default, given -> given || default end)
        stream(Vws.Ops.MTConnect.Stream.sample(agent, p))

      p[:heartbeat] != nil ->
        bad(agent, p, "INVALID_REQUEST", "'heartbeat' is for streaming: give 'interval' too")

      true ->
        Agent.sample(agent, p[:from], p[:count], p.device,
          to: p[:to],
          path: p[:path],
          format: p.format
        )
    end
  end

  defp stream({:ok, first, more}), do: {:stream, first, more}
  defp stream({:error, _, _} = error), do: error

  defp bad(agent, p, code, text),
    do: {:error, 400, Agent.error(agent, code, text, p.format)}

  defp range(agent, p, name, value),
    do: bad(agent, p, "OUT_OF_RANGE", "'#{name}' must be between 0 and #{@max_ms}, not #{value}")

  defp known_params(request, q) do
    case Map.keys(q) -- Map.fetch!(@params, request) do
      [] ->
        :ok

      unknown ->
        {:bad, "INVALID_REQUEST",
         "#{request} takes no parameter #{Enum.map_join(unknown, ", ", &"'#{&1}'")}"}
    end
  end

  @integers ~w(from count to at interval heartbeat)

  defp params(q) do
    Enum.reduce_while(q, {:ok, %{}}, fn
      {k, v}, {:ok, acc} when k in @integers ->
        case Integer.parse(String.trim(v)) do
          {n, ""} -> {:cont, {:ok, Map.put(acc, String.to_atom(k), n)}}
          _ -> {:halt, {:bad, "INVALID_REQUEST", "'#{k}' must be an integer, not '#{v}'"}}
        end

      {"path", v}, {:ok, acc} ->
        {:cont, {:ok, Map.put(acc, :path, v)}}

      {"removed", v}, {:ok, acc} when v in ["true", "false"] ->
        {:cont, {:ok, Map.put(acc, :removed, v == "true")}}

      {"removed", v}, _acc ->
        {:halt, {:bad, "INVALID_REQUEST", "'removed' must be true or false, not '#{v}'"}}

      {k, v}, {:ok, acc} when k in ["type", "device"] ->
        {:cont, {:ok, Map.put(acc, String.to_atom(k), v)}}

      {"format", _}, {:ok, acc} ->
        {:cont, {:ok, acc}}
    end)
  end

  # XML unless JSON is asked for: `format=json`, or an Accept header naming JSON before XML
  defp format(_r, %{"format" => "json"}), do: {:ok, :json}
  defp format(_r, %{"format" => "xml"}), do: {:ok, :xml}

  defp format(_r, %{"format" => other}),
    do: {:bad, "INVALID_REQUEST", "'format' must be xml or json, not '#{other}'"}

  defp format(r, _q) do
    accept = String.downcase(get_in(r, [:headers, "accept"]) || "")

    json = :binary.match(accept, "json")
    xml = :binary.match(accept, "xml")

    case {json, xml} do
      {{j, _}, {x, _}} when j < x -> {:ok, :json}
      {{_, _}, :nomatch} -> {:ok, :json}
      _ -> {:ok, :xml}
    end
  end

  defp mime(:json), do: "application/json"
  defp mime(:xml), do: "application/xml"

  defp mtc_error(%{agent: agent}, fmt, status, code, text) do
    fmt = with({:ok, f} <- fmt, do: f, else: (_ -> :xml))
    {status, mime(fmt), Agent.error(agent, code, text, fmt)}
  end
end
