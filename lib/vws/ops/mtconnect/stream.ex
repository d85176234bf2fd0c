defmodule Vws.Ops.MTConnect.Stream do
  @moduledoc """
  MTConnect streaming (`interval=` on `/sample` and `/current`), as the reference agent does it:
  the web server sends one document per part of a `multipart/x-mixed-replace` answer
  (`Vws.Ops.Web.Conn`), and these loops say which documents and when.

    * `sample/4` — from `from` (default: the observations after the request), each part the
      next page of at most `count` observations, sent as soon as there are new ones but never
      less than `interval` ms after the part before; when nothing new comes for `heartbeat` ms,
      an empty document (the same header, no observations) says the agent is alive;
    * `current/3` — the current document every `interval` ms.

  A part that cannot be made (the client fell so far behind that its next sequence has left the
  buffer) is sent as the `MTConnectError` it is, and the stream ends, as in cppagent.
  """

  alias Vws.Ops.MTConnect.Agent

  @typedoc "Sends one part; anything but `:ok` ends the stream (the client is gone)."
  @type send_part :: (iodata -> :ok | {:error, term})

  @doc """
  The first part of a sample stream and the loop that sends the rest: `{:ok, first, more}` or
  the error answer of the request. `params`: `from`, `count`, `interval`, `heartbeat`, `device`,
  `path`, `format`.
  """
  @spec sample(Agent.agent(), map) ::
          {:ok, iodata, (send_part -> :ok)} | {:error, integer, iodata}
  def sample(agent, p) do
    from = p[:from] || Agent.sequences(agent).next

    case page(agent, from, p) do
      {:ok, doc, next} ->
        {:ok, doc, fn send -> sample_loop(agent, p, next, now(), send) end}

      {:error, _, _} = error ->
        error
    end
  end

  defp page(agent, from, p) do
    Agent.sample_page(agent, from, p[:count], p[:device], path: p[:path], format: p[:format])
  end

  defp sample_loop(agent, p, next, sent_at, send) do
    case Agent.await(agent, next, p.heartbeat) do
      :ok ->
        # not more often than every `interval` ms
        wait = sent_at + p.interval - now()
        if wait > 0, do: Process.sleep(wait)
        part(agent, p, next, send)

      :timeout ->
        # a heartbeat: the page from `next` (empty, or what came at the last moment)
        part(agent, p, next, send)
    end
  end

  defp part(agent, p, next, send) do
    case page(agent, next, p) do
      {:ok, doc, next} ->
        case send.(doc) do
          :ok -> sample_loop(agent, p, next, now(), send)
          _closed -> :ok
        end

      {:error, _status, doc} ->
        _ = send.(doc)
        :ok
    end
  end

  @doc "The first part of a current stream and the loop that sends the rest (see `sample/2`)."
  @spec current(Agent.agent(), map) ::
          {:ok, iodata, (send_part -> :ok)} | {:error, integer, iodata}
  def current(agent, p) do
    opts = [path: p[:path], format: p[:format]]

    case Agent.current(agent, p[:device], opts) do
      {:ok, doc} -> {:ok, doc, fn send -> current_loop(agent, p, opts, send) end}
      {:error, _, _} = error -> error
    end
  end

  defp current_loop(agent, p, opts, send) do
    Process.sleep(max(p.interval, 10))

    case Agent.current(agent, p[:device], opts) do
      {:ok, doc} ->
        if send.(doc) == :ok, do: current_loop(agent, p, opts, send), else: :ok

      {:error, _, doc} ->
        _ = send.(doc)
        :ok
    end
  end

  defp now, do: System.monotonic_time(:millisecond)
end
