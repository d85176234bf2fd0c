defmodule Vws.Ops.Web.Snapshot do
  @moduledoc """
  The dashboard state of one `Vws.Ops.Web` server (`Vws.Ops.Web.State.build/1`, encoded as JSON), built
  at most once every `:max_age` ms (default 200, half the page's polling interval) whatever the
  number of clients asking: every build asks the workstations — SUN_COMM among them — for their
  state, so without it each HTTP request was work for the processes that serve the WC, and HTTP
  load became WC latency (`bench/http_load.exs`). Callers that ask while the state is fresh get
  the same bytes.

  A build that fails (a workstation's part crashing while it is asked) answers
  `{:error, text}` and is tried again by the next caller; it never takes this process — nor,
  through its supervisor, the listener — down.
  """
  use GenServer

  @doc false
  def child_spec(opts), do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}}

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts),
    do: GenServer.start_link(__MODULE__, opts, name: Keyword.fetch!(opts, :name))

  @doc "The state as JSON, at most `max_age` ms old, or why it could not be built."
  @spec json(GenServer.server()) :: {:ok, binary} | {:error, String.t()}
  def json(server), do: GenServer.call(server, :json, 15_000)

  @impl true
  def init(opts) do
    # State.build's tasks are linked: one that crashes must not take this process with it
    Process.flag(:trap_exit, true)
    # HTTP work yields to the workstations (Vws.Ops.Web.Server's moduledoc)
    Process.flag(:priority, :low)

    {:ok,
     %{
       control: Keyword.get(opts, :control, false),
       # the program library sections, read again only as often as their size allows (State)
       library_cache: :ets.new(:vws_web_library_cache, [:public]),
       max_age: Keyword.get(opts, :max_age, 200),
       built_at: nil,
       json: nil
     }}
  end

  @impl true
  def handle_call(:json, _from, s) do
    now = System.monotonic_time(:millisecond)

    if s.built_at != nil and now - s.built_at < s.max_age do
      {:reply, {:ok, s.json}, s}
    else
      case build(s.control, s.library_cache) do
        {:ok, json} ->
          {:reply, {:ok, json}, %{s | json: json, built_at: System.monotonic_time(:millisecond)}}

        error ->
          {:reply, error, s}
      end
    end
  end

  @impl true
  def handle_info({:EXIT, _task, _reason}, s), do: {:noreply, s}
  def handle_info(_msg, s), do: {:noreply, s}

  defp build(control, cache) do
    state = Vws.Ops.Web.State.build(control: control, library_cache: cache)
    {:ok, IO.iodata_to_binary(Vws.Ops.Web.JSON.encode(state))}
  rescue
    e -> {:error, "the state could not be built: " <> Exception.message(e)}
  catch
    :exit, reason -> {:error, "the state could not be built: " <> inspect(reason, limit: 5)}
  end
end
