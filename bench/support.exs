# Shared by the benchmarks (Code.require_file("support.exs", __DIR__)): the machine block and
# percentiles. Not a benchmark itself.

defmodule Vws.Bench do
  @moduledoc false

  @doc "The lines describing the machine and the runtime, for the top of a figure block."
  def machine do
    cpu =
      case File.read("/proc/cpuinfo") do
        {:ok, info} ->
          Regex.run(~r/model name\s*:\s*(.*)/, info, capture: :all_but_first)
          |> List.wrap()
          |> List.first()

        _ ->
          nil
      end

    load =
      case File.read("/proc/loadavg") do
        {:ok, text} -> text |> String.split() |> Enum.take(3) |> Enum.join(" ")
        _ -> "?"
      end

    [
      "  machine        #{cpu || "unknown CPU"}, #{:erlang.system_info(:logical_processors_available)} cores " <>
        "(#{System.schedulers_online()} schedulers), #{:erlang.system_info(:system_architecture)}",
      "  runtime        Erlang/OTP #{System.otp_release()} (erts #{:erlang.system_info(:version)}), Elixir #{System.version()}",
      "  load average   #{load} at the start (the machine is shared: other work shows in the figures)"
    ]
  end

  @doc "The `p` quantile (0..1) of a list of numbers (nearest rank)."
  def pct([], _p), do: nil

  def pct(list, p) do
    sorted = Enum.sort(list)
    Enum.at(sorted, min(length(sorted) - 1, max(0, ceil(length(sorted) * p) - 1)))
  end

  @doc "`p50 … p99 … max …` of a list, each formatted by `fmt`."
  def summary(list, fmt \\ &to_string/1) do
    "p50 #{fmt.(pct(list, 0.50))}  p99 #{fmt.(pct(list, 0.99))}  max #{fmt.(Enum.max(list))}"
  end

  @doc "Runs `fun` `n` times; returns the wall time in µs."
  def time_n(n, fun) do
    {us, _} = :timer.tc(fn -> loop(n, fun) end)
    us
  end

  defp loop(0, _fun), do: :ok

  defp loop(n, fun) do
    fun.()
    loop(n - 1, fun)
  end

  @doc """
  Calls `fun` in a loop for about `ms` milliseconds (after a warm-up of a tenth of that) and
  returns `{calls, µs}`: rounds of doubling size, so the clock is read rarely.
  """
  def run_for(ms, fun) do
    _ = run_rounds(div(ms, 10), fun, 1, 0, 0)
    run_rounds(ms, fun, 1, 0, 0)
  end

  defp run_rounds(ms, fun, batch, calls, us) do
    if us >= ms * 1_000 do
      {calls, us}
    else
      t = time_n(batch, fun)
      run_rounds(ms, fun, min(batch * 2, 100_000), calls + batch, us + t)
    end
  end

  @doc """
  The best of `k` runs of `run_for(ms / k, fun)`, as `{calls, µs}`: on a shared machine other
  work only ever slows a run down, so the fastest is the codec's own speed.
  """
  def best_of(k, ms, fun) do
    1..k
    |> Enum.map(fn _ -> run_for(max(div(ms, k), 1), fun) end)
    |> Enum.max_by(fn {calls, us} -> calls / us end)
  end

  @doc """
  The mean utilisation (0..1) of the normal schedulers since `sample` (`:scheduler.sample/0`);
  `:scheduler.utilization/1`'s `total` also averages in the idle dirty schedulers.
  """
  def normal_utilization(sample) do
    normal = for {:normal, _id, u, _} <- :scheduler.utilization(sample), do: u
    Enum.sum(normal) / max(length(normal), 1)
  end

  @doc """
  The CEC's own memory of a workstation, in bytes: the processes of its supervision tree, the
  unnamed processes they are linked to (links, SUN_COMM's acceptor, command tasks) and the ETS
  tables they own.
  """
  def cec_memory(ws) do
    walk = fn walk, sup, acc ->
      Enum.reduce(Supervisor.which_children(sup), acc, fn
        {_, pid, :supervisor, _}, acc when is_pid(pid) -> walk.(walk, pid, MapSet.put(acc, pid))
        {_, pid, _worker, _}, acc when is_pid(pid) -> MapSet.put(acc, pid)
        _, acc -> acc
      end)
    end

    case Vws.CEC.Workstation.whereis(ws) do
      nil ->
        0

      sup ->
        tree = walk.(walk, sup, MapSet.new([sup]))

        linked =
          for pid <- tree,
              {:links, links} <- [Process.info(pid, :links)],
              other <- links,
              is_pid(other),
              not MapSet.member?(tree, other),
              # not the node's shared processes (registry partitions, supervisors): named ones
              Process.info(other, :registered_name) == {:registered_name, []},
              into: MapSet.new(),
              do: other

        pids = MapSet.union(tree, linked)

        procs = Enum.sum(for pid <- pids, {:memory, m} <- [Process.info(pid, :memory)], do: m)

        tables =
          Enum.sum(
            for t <- :ets.all(),
                MapSet.member?(pids, :ets.info(t, :owner)),
                do: :ets.info(t, :memory) * :erlang.system_info(:wordsize)
          )

        procs + tables
    end
  end

  @doc "Asks `fun` every 50 ms until it is true (`:ok`) or `ms` have passed (`:timeout`)."
  def wait_until(fun, ms) do
    deadline = System.monotonic_time(:millisecond) + ms

    Stream.repeatedly(fn ->
      cond do
        fun.() -> :ok
        System.monotonic_time(:millisecond) > deadline -> :timeout
        true -> Process.sleep(50) && nil
      end
    end)
    |> Enum.find(& &1)
  end

  @doc "Everything an OS process opened with `Port.open/2` (`:exit_status`) writes until it exits (or `ms` pass quietly)."
  def port_output(port, ms) do
    Stream.repeatedly(fn ->
      receive do
        {^port, {:data, data}} -> data
        {^port, {:exit_status, _}} -> :eof
      after
        ms -> :eof
      end
    end)
    |> Enum.take_while(&(&1 != :eof))
    |> Enum.join()
  end

  @doc """
  A raw WC on TCP `port` (passive, nodelay): a function that sends `status` `n` times, one every
  2 ms, and answers the µs from each send to its reply line.
  """
  def wc_client(port, status) do
    {:ok, wc} =
      :gen_tcp.connect({127, 0, 0, 1}, port, [
        :binary,
        active: false,
        nodelay: true,
        packet: :line
      ])

    fn n ->
      for _ <- 1..n do
        t0 = System.monotonic_time()
        :ok = :gen_tcp.send(wc, status)
        {:ok, _line} = :gen_tcp.recv(wc, 0, 10_000)
        t1 = System.monotonic_time()
        Process.sleep(2)
        System.convert_time_unit(t1 - t0, :native, :nanosecond) / 1_000
      end
    end
  end

  @doc "A number with thousands separators."
  def thousands(n) when is_float(n), do: thousands(round(n))

  def thousands(n) when is_integer(n) do
    n
    |> Integer.to_string()
    |> String.reverse()
    |> String.replace(~r/(\d{3})(?=\d)/, "\\1,")
    |> String.reverse()
  end

  @doc "µs (native integer) with one decimal as text."
  def us(x) when is_integer(x), do: Integer.to_string(x)
  def us(x) when is_float(x), do: :erlang.float_to_binary(x, decimals: 1)

  @doc "MB from bytes, with one decimal."
  def mb(bytes), do: :erlang.float_to_binary(bytes / 1_048_576, decimals: 1)

  @doc "Verdict text for a target."
  def verdict(true, _missed_by), do: "MET"
  def verdict(false, missed_by), do: "MISSED by #{missed_by}"
end
