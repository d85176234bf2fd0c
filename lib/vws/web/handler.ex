defmodule Vws.Web.Handler do
  @moduledoc """
  The routes of `Vws.Web`: the dashboard page, the JSON state, the control action and the
  MTConnect agent. `Vws.Web.Server` reads a request's head, asks `authorize/2` whether it may go
  on — before a byte of its body is read — and then `handle/2` for the answer.

  A request is a map: `method` ("GET"…), `path`, `query` (decoded map), `headers` (lower-case
  names → values), and `body` for `handle/2`. An answer is `{status, content_type, body}` or
  `{status, content_type, body, extra_headers}`.

  ## Tokens

    * the **control token** (`:token`): `POST /api/status` needs it in the `x-vws-token` header;
      without a control token configured every control request is refused 403;
    * the **read token** (`:read_token`, optional): when set, every other path needs it (or the
      control token) — as the password of HTTP Basic authentication (any user name; a browser
      asks once and sends it with the page's own requests) or in the `x-vws-token` header;
      otherwise 401. Without one the reads are open to whoever reaches the port.
  """

  alias Vws.MTConnect.Agent

  @control ["api", "status"]

  @doc """
  Whether a request may go on, judged on its head alone: `:ok`, or `{:deny, answer}` (401 for a
  read without the read token, 403 for control without the control token).
  """
  @spec authorize(map, map) :: :ok | {:deny, tuple}
  def authorize(%{method: method, path: path, headers: headers}, settings) do
    if method == "POST" and segments(path) == @control do
      authorize_control(headers, settings)
    else
      authorize_read(headers, settings)
    end
  end

  defp authorize_control(headers, %{token: token}) do
    given = headers["x-vws-token"]

    cond do
      token == nil ->
        {:deny,
         {403, "application/json",
          Vws.JSON.encode(%{error: "read-only: no control token configured"})}}

      given == nil or not secure_equal?(given, token) ->
        {:deny,
         {403, "application/json",
          Vws.JSON.encode(%{error: "control needs the right x-vws-token"})}}

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

  defp route(m, [], _q, _r, _s) when m in @read,
    do: {200, "text/html; charset=utf-8", Vws.Web.Page.html()}

  defp route(m, ["api", "state"], _q, _r, s) when m in @read,
    do: state(s)

  defp route("POST", @control, q, _r, _s), do: status_query(q)

  defp route(m, [request], q, _r, s) when m in @read and request in ~w(probe current sample),
    do: mtconnect(request, nil, q, s)

  defp route(m, [device, request], q, _r, s)
       when m in @read and request in ~w(probe current sample) and device != "api",
       do: mtconnect(request, device, q, s)

  defp route(m, _path, _q, _r, _s) when m in @read, do: {404, "text/plain", "not found"}
  defp route(_m, _path, _q, _r, _s), do: {405, "text/plain", "method not allowed"}

  defp state(s) do
    case Vws.Web.Snapshot.json(s.snapshot) do
      {:ok, json} -> {200, "application/json", json}
      {:error, why} -> {503, "application/json", Vws.JSON.encode(%{error: why})}
    end
  end

  ## Control (authorized by authorize/2)

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
