defmodule Vws.Test.LineRelay do
  @moduledoc """
  A line relay between a WC and SUN_COMM that can damage or drop chosen lines, to show what the
  client does with a bad line: `arm(relay, :to_cec | :to_wc, :corrupt | :drop | {:replace,
  fun}, pred, times)` — `{:replace, fun}` sends `fun.(line)` instead (a damage the BCC cannot see).
  """
  use GenServer

  alias Vws.Links.Transport
  alias Vws.Codecs.WC.LineDecoder

  def start_link(upstream, name), do: GenServer.start_link(__MODULE__, {upstream, name})

  def arm(relay, direction, action, pred \\ fn _ -> true end, times \\ 1),
    do: GenServer.call(relay, {:arm, {direction, action, pred, times}})

  @doc "The line with one character in its middle changed: its BCC no longer matches."
  def corrupt(line) do
    chars = String.to_charlist(line)
    i = Enum.find(div(length(chars), 2)..(length(chars) - 1), &(Enum.at(chars, &1) != ?*))
    List.to_string(List.update_at(chars, i, &if(&1 == ?Q, do: ?R, else: ?Q)))
  end

  @impl true
  def init({upstream, name}) do
    {:ok, listener} = Transport.listen("loopback:#{name}")
    me = self()

    spawn_link(fn -> accept_loop(listener, me) end)

    {:ok, %{upstream: upstream, listener: listener, down: nil, up: nil, dec: %{}, rules: []}}
  end

  defp accept_loop(listener, relay) do
    {:ok, conn} = Transport.accept(listener, :infinity)
    :ok = Transport.controlling_process(conn, relay)
    send(relay, {:accepted, conn})
    accept_loop(listener, relay)
  end

  @impl true
  def handle_call({:arm, rule}, _from, s), do: {:reply, :ok, %{s | rules: s.rules ++ [rule]}}

  @impl true
  def handle_info({:accepted, down}, s) do
    # a new WC connection replaces the previous pair, as SUN_COMM's takeover would
    if s.down, do: Transport.close(s.down)
    if s.up, do: Transport.close(s.up)
    # SUN_COMM listens only after OK_TO_PROCEED: a relay started with the workstation may be early
    {:ok, up} = connect_upstream(s.upstream, 250)
    Transport.activate(down)
    Transport.activate(up)

    {:noreply,
     %{s | down: down, up: up, dec: %{to_cec: LineDecoder.new(), to_wc: LineDecoder.new()}}}
  end

  def handle_info(msg, %{down: down, up: up} = s) when down != nil do
    case {Transport.handle_message(down, msg), Transport.handle_message(up, msg)} do
      {:unknown, :unknown} -> {:noreply, s}
      {:unknown, result} -> from(up, down, :to_wc, result, s)
      {result, _} -> from(down, up, :to_cec, result, s)
    end
  end

  def handle_info(_msg, s), do: {:noreply, s}

  defp connect_upstream(endpoint, tries) do
    case Transport.connect(endpoint) do
      {:error, _} when tries > 0 -> Process.sleep(20) && connect_upstream(endpoint, tries - 1)
      result -> result
    end
  end

  defp from(src, dst, direction, {:data, bytes}, s) do
    {lines, dec} = LineDecoder.feed(s.dec[direction], bytes)
    Transport.activate(src)

    s =
      Enum.reduce(lines, %{s | dec: Map.put(s.dec, direction, dec)}, fn line, s ->
        {action, s} = rule_for(direction, line, s)

        case action do
          :drop -> :ok
          :corrupt -> Transport.send(dst, [corrupt(line), "\r\n"])
          {:replace, fun} -> Transport.send(dst, [fun.(line), "\r\n"])
          :pass -> Transport.send(dst, [line, "\r\n"])
        end

        s
      end)

    {:noreply, s}
  end

  defp from(_src, dst, _direction, _closed_or_error, s) do
    Transport.close(dst)
    {:noreply, s}
  end

  defp rule_for(direction, line, s) do
    case Enum.split_while(s.rules, fn {d, _, pred, _} -> not (d == direction and pred.(line)) end) do
      {_, []} ->
        {:pass, s}

      {before, [{d, action, pred, times} | rest]} ->
        left =
          if times == :infinity,
            do: [{d, action, pred, times}],
            else: if(times > 1, do: [{d, action, pred, times - 1}], else: [])

        {action, %{s | rules: before ++ left ++ rest}}
    end
  end
end
