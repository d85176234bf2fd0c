defmodule Vws.Test.ModuleOrder do
  @moduledoc """
  The suite's async modules started longest first (issue 26: the suite under 3 minutes).

  ExUnit 1.14 starts running async modules while `mix test` is still loading the test files, each
  as its file happens to load (and, once all places are taken, the one loaded *last*: its queue is
  a stack). Loading 180 files beside 16 running modules took up to 85 s, and the long modules
  loaded late (the crash campaign, the bit-flip tests) started two minutes in and ended the async
  phase alone, 20–30 s after the rest.

  This is an ExUnit formatter, first in the list (`test/test_helper.exs`): ExUnit starts its
  formatters before its first module, and this one's start waits until every file is loaded
  (about 11 s on this machine, with both cores to itself), then puts ExUnit's queue in the order
  of `test/module_seconds.txt` — the time of each module in a whole run here — longest first. A
  module not listed counts as short until the file is written again:
  `VWS_MODULE_SECONDS=write mix test` (a whole run). It changes when each module starts, never
  what runs or how. A `--formatter` on the command line replaces the configured formatters, this
  one included: the modules then run in ExUnit's own order.

  It relies on `ExUnit.Server`'s state, which is not public: if its shape is not the one of
  Elixir 1.14 (a list in `:async_modules`, `:loaded` becoming `:done`), this does nothing.
  """

  @file_name Path.expand("../module_seconds.txt", __DIR__)

  @doc "The file of recorded module times."
  def file_name, do: @file_name

  @doc """
  A formatter whose start waits until every test file is loaded, then puts ExUnit's async queue
  in the recorded order (ExUnit starts its formatters before its first module: while this
  waits, no module starts).
  """
  use GenServer

  @impl true
  def init(_opts) do
    seconds = read()
    if map_size(seconds) > 0, do: order(seconds, System.monotonic_time(:millisecond) + 300_000)
    {:ok, nil}
  end

  @impl true
  def handle_cast(_event, state), do: {:noreply, state}

  @doc "The recorded seconds of each module, by name."
  def read do
    case File.read(@file_name) do
      {:ok, text} ->
        for line <- String.split(text, "\n", trim: true),
            not String.starts_with?(line, "#"),
            [s, name] <- [String.split(line, " ", parts: 2)],
            {seconds, ""} <- [Float.parse(s)],
            into: %{},
            do: {name, seconds}

      {:error, _} ->
        %{}
    end
  end

  defp order(seconds, deadline) do
    case :sys.get_state(ExUnit.Server) do
      %{async_modules: modules, loaded: :done} when is_list(modules) ->
        :sys.replace_state(ExUnit.Server, fn s ->
          %{
            s
            | async_modules:
                Enum.sort_by(s.async_modules, &Map.get(seconds, inspect(&1), 0.0), :desc)
          }
        end)

      %{async_modules: modules} when is_list(modules) ->
        if System.monotonic_time(:millisecond) < deadline do
          Process.sleep(10)
          order(seconds, deadline)
        end

      _ ->
        :ok
    end
  end

  defmodule Recorder do
    @moduledoc """
    An ExUnit formatter that writes each module's time to `test/module_seconds.txt` at the end
    of a run (added by `test/test_helper.exs` when `VWS_MODULE_SECONDS=write`).
    """
    use GenServer

    @impl true
    def init(_opts), do: {:ok, %{started: %{}, seconds: %{}}}

    @impl true
    def handle_cast({:module_started, %{name: name}}, s),
      do: {:noreply, put_in(s.started[name], System.monotonic_time(:millisecond))}

    def handle_cast({:module_finished, %{name: name}}, s) do
      ms = System.monotonic_time(:millisecond) - Map.get(s.started, name, 0)
      {:noreply, put_in(s.seconds[inspect(name)], ms / 1000)}
    end

    def handle_cast({:suite_finished, _}, s) do
      lines =
        s.seconds
        |> Enum.sort_by(fn {_name, seconds} -> -seconds end)
        |> Enum.map(fn {name, seconds} ->
          "#{:erlang.float_to_binary(seconds, decimals: 1)} #{name}\n"
        end)

      File.write!(
        Vws.Test.ModuleOrder.file_name(),
        [
          "# seconds of each test module in a whole `mix test` (Vws.Test.ModuleOrder), written by\n",
          "# `VWS_MODULE_SECONDS=write mix test` on #{System.schedulers_online()} schedulers\n"
          | lines
        ]
      )

      {:noreply, s}
    end

    def handle_cast(_event, s), do: {:noreply, s}
  end
end
