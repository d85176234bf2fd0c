defmodule Vws.Test.FlipRelay do
  @moduledoc """
  A TCP relay that flips chosen bits of the bytes it carries, for any byte-stream link (the WC
  link, DNC, HPIB). It listens on `127.0.0.1:0` and, for every connection it accepts, dials the
  target and carries bytes both ways: `:to_target` (from the end that connected) and
  `:to_client` (back).

  What it damages is a plan, set with `plan/2` (it applies from then on):

    * `{:bytes, [{direction, index, mask}]}` — byte number `index` (0-based, counted per
      direction over every connection since the plan was set) goes out XOR `mask`: one bit for
      a single-bit flip, several for a burst;
    * `{:lines, [{direction, regex, fun}]}` — in `direction`, every line (up to LF, without
      it) matching `regex` goes out as `fun.(line)` (one or more bits of it flipped, or the
      line unchanged); the first rule that matches applies;
    * `:none`.

  `counts/1` returns the bytes carried per direction since the plan was set, and how many
  flips were made.
  """
  use GenServer

  def start_link(target), do: GenServer.start_link(__MODULE__, target)

  @doc "The endpoint to connect to instead of the target."
  def endpoint(relay), do: GenServer.call(relay, :endpoint)

  def plan(relay, plan), do: GenServer.call(relay, {:plan, plan})
  def counts(relay), do: GenServer.call(relay, :counts)

  @doc "Closes every connection (both legs)."
  def cut(relay), do: GenServer.call(relay, :cut)

  @doc "`line` with bit `bit` (0–7) of byte `index` inverted."
  def flip(line, index, bit) do
    <<pre::binary-size(index), byte, post::binary>> = line
    <<pre::binary, Bitwise.bxor(byte, Bitwise.bsl(1, bit)), post::binary>>
  end

  @doc """
  A PropEr generator of byte bursts for `{:bytes, _}` plans over traffic of `to_target` and
  `to_client` bytes: one byte of either direction XOR a random mask, and often the next byte of
  that direction with a mask of its own.
  """
  def burst(to_target, to_client) do
    :proper_types.bind(
      :proper_types.tuple([
        :proper_types.elements([:to_target, :to_client]),
        :proper_types.range(0, 1_000_000),
        :proper_types.range(1, 255),
        :proper_types.range(0, 255)
      ]),
      fn {dir, r, mask, next_mask} ->
        n = if dir == :to_target, do: to_target, else: to_client
        index = rem(r, n)
        next = if index + 1 < n and next_mask > 0, do: [{dir, index + 1, next_mask}], else: []
        :proper_types.exactly([{dir, index, mask} | next])
      end,
      false
    )
  end

  @impl true
  def init(target) do
    %URI{host: host, port: port} = URI.parse(target)
    {:ok, listener} = :gen_tcp.listen(0, [:binary, active: false, ip: {127, 0, 0, 1}])
    {:ok, lport} = :inet.port(listener)
    me = self()

    spawn_link(fn -> accept_loop(listener, me) end)

    {:ok,
     %{
       target: {String.to_charlist(host), port},
       endpoint: "tcp://127.0.0.1:#{lport}",
       pairs: %{},
       plan: :none,
       counts: %{to_target: 0, to_client: 0, flips: 0},
       partial: %{to_target: "", to_client: ""}
     }}
  end

  defp accept_loop(listener, relay) do
    {:ok, sock} = :gen_tcp.accept(listener)
    :ok = :gen_tcp.controlling_process(sock, relay)
    send(relay, {:accepted, sock})
    accept_loop(listener, relay)
  end

  @impl true
  def handle_call(:endpoint, _from, s), do: {:reply, s.endpoint, s}

  def handle_call({:plan, plan}, _from, s),
    do:
      {:reply, :ok,
       %{
         s
         | plan: plan,
           counts: %{to_target: 0, to_client: 0, flips: 0},
           partial: %{to_target: "", to_client: ""}
       }}

  def handle_call(:counts, _from, s), do: {:reply, s.counts, s}

  def handle_call(:cut, _from, s) do
    for {sock, _} <- s.pairs, do: :gen_tcp.close(sock)
    {:reply, :ok, %{s | pairs: %{}}}
  end

  @impl true
  def handle_info({:accepted, client}, s) do
    {host, port} = s.target

    case :gen_tcp.connect(host, port, [:binary, active: true, nodelay: true], 5_000) do
      {:ok, up} ->
        :ok = :inet.setopts(client, active: true, nodelay: true)

        pairs =
          s.pairs
          |> Map.put(client, {up, :to_target})
          |> Map.put(up, {client, :to_client})

        {:noreply, %{s | pairs: pairs}}

      {:error, _} ->
        :gen_tcp.close(client)
        {:noreply, s}
    end
  end

  def handle_info({:tcp, sock, bytes}, s) do
    case Map.fetch(s.pairs, sock) do
      {:ok, {dst, dir}} ->
        {out, s} = damage(dir, bytes, s)
        if out != "", do: :gen_tcp.send(dst, out)
        {:noreply, s}

      :error ->
        {:noreply, s}
    end
  end

  def handle_info({:tcp_closed, sock}, s) do
    case Map.pop(s.pairs, sock) do
      {{other, _}, pairs} ->
        :gen_tcp.close(other)
        {:noreply, %{s | pairs: Map.delete(pairs, other)}}

      {nil, _} ->
        {:noreply, s}
    end
  end

  def handle_info(_msg, s), do: {:noreply, s}

  defp damage(dir, bytes, %{plan: {:bytes, flips}} = s) do
    start = s.counts[dir]

    {out, n} =
      bytes
      |> :binary.bin_to_list()
      |> Enum.with_index(start)
      |> Enum.map_reduce(0, fn {byte, i}, n ->
        case for({^dir, ^i, mask} <- flips, do: mask) do
          [] -> {byte, n}
          masks -> {Enum.reduce(masks, byte, &Bitwise.bxor/2), n + 1}
        end
      end)

    counts = %{s.counts | dir => start + byte_size(bytes), flips: s.counts.flips + n}
    {:binary.list_to_bin(out), %{s | counts: counts}}
  end

  defp damage(dir, bytes, %{plan: {:lines, rules}} = s) do
    data = s.partial[dir] <> bytes
    parts = String.split(data, "\n")
    {lines, [rest]} = Enum.split(parts, -1)

    {out, n} =
      Enum.map_reduce(lines, 0, fn line, n ->
        case Enum.find(rules, fn {d, regex, _} -> d == dir and Regex.match?(regex, line) end) do
          nil ->
            {line <> "\n", n}

          {_, _, fun} ->
            out = fun.(line)
            {out <> "\n", if(out == line, do: n, else: n + 1)}
        end
      end)

    counts = %{s.counts | dir => s.counts[dir] + byte_size(bytes), flips: s.counts.flips + n}
    {IO.iodata_to_binary(out), %{s | partial: Map.put(s.partial, dir, rest), counts: counts}}
  end

  defp damage(dir, bytes, s) do
    {bytes, %{s | counts: Map.update!(s.counts, dir, &(&1 + byte_size(bytes)))}}
  end
end
