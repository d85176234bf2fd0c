defmodule Vws.Web.Snapshot do
  @moduledoc """
  The dashboard state of one `Vws.Web` server (`Vws.Web.State.build/1`, encoded as JSON), built
  at most once every `:max_age` ms (default 200, half the page's polling interval) whatever the
  number of clients asking: every build asks the workstations — SUN_COMM among them — for their
  state, so without it each HTTP request was work for the processes that serve the WC, and HTTP
  load became WC latency (`bench/http_load.exs`). Callers that ask while the state is fresh get
  the same bytes.
  """
  use GenServer

  @doc false
  def child_spec(opts), do: %{id: __MODULE__, start: {__MODULE__, :start_link, [opts]}}

  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts),
    do: GenServer.start_link(__MODULE__, opts, name: Keyword.fetch!(opts, :name))

  @doc "The state as JSON, at most `max_age` ms old."
  @spec json(GenServer.server()) :: binary
  def json(server), do: GenServer.call(server, :json, 15_000)

  @impl true
  def init(opts) do
    {:ok,
     %{
       control: Keyword.get(opts, :control, false),
       max_age: Keyword.get(opts, :max_age, 200),
       built_at: nil,
       json: nil
     }}
  end

  @impl true
  def handle_call(:json, _from, s) do
    now = System.monotonic_time(:millisecond)

    if s.built_at != nil and now - s.built_at < s.max_age do
      {:reply, s.json, s}
    else
      json = IO.iodata_to_binary(Vws.JSON.encode(Vws.Web.State.build(control: s.control)))
      {:reply, json, %{s | json: json, built_at: System.monotonic_time(:millisecond)}}
    end
  end
end
