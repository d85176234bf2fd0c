defmodule Vws.Test.FakeDDCMP do
  @moduledoc """
  A stand-in for a `Vws.DDCMP` link in tests of the layers above it: the same client API
  (`start_link/1`, `send_data/2`, `restart/1`, `info/1`) and the same messages to the owner
  (`{:ddcmp, link, :up | {:data, bin} | {:down, reason} | :peer_restarted}`), no bytes, no
  timers.

  The test plays the peer. Start it with `endpoint: {:test, test_pid}`: the test receives
  `{:fake_ddcmp, :started, link}` once, `{:fake_ddcmp, link, {:sent, binary}}` for every message
  the owner sends and `{:fake_ddcmp, link, :restart}` for `restart/1`, and drives the owner with
  `up/1`, `deliver/2`, `down/2` and `peer_restarted/1`.
  """
  use GenServer

  def start_link(opts), do: GenServer.start_link(__MODULE__, opts)

  def send_data(link, iodata, _opts \\ []),
    do: GenServer.call(link, {:send, IO.iodata_to_binary(iodata)})

  def restart(link), do: GenServer.call(link, :restart)
  def info(link), do: GenServer.call(link, :info)

  @doc "Tells the owner the link is up."
  def up(link), do: GenServer.call(link, {:to_owner, :up})
  @doc "Delivers a data message to the owner."
  def deliver(link, bin), do: GenServer.call(link, {:to_owner, {:data, IO.iodata_to_binary(bin)}})
  @doc "Tells the owner the link went down."
  def down(link, reason), do: GenServer.call(link, {:to_owner, {:down, reason}})
  @doc "Tells the owner the peer restarted."
  def peer_restarted(link), do: GenServer.call(link, {:to_owner, :peer_restarted})

  @impl true
  def init(opts) do
    {:test, test} = Keyword.fetch!(opts, :endpoint)
    send(test, {:fake_ddcmp, :started, self()})
    {:ok, %{owner: Keyword.fetch!(opts, :owner), test: test, sent: 0, opts: opts}}
  end

  @impl true
  def handle_call({:send, bin}, _from, s) do
    send(s.test, {:fake_ddcmp, self(), {:sent, bin}})
    {:reply, :ok, %{s | sent: s.sent + 1}}
  end

  def handle_call(:restart, _from, s) do
    send(s.test, {:fake_ddcmp, self(), :restart})
    {:reply, :ok, s}
  end

  def handle_call(:info, _from, s), do: {:reply, %{state: :fake, sent: s.sent}, s}

  def handle_call({:to_owner, msg}, _from, s) do
    send(s.owner, {:ddcmp, self(), msg})
    {:reply, :ok, s}
  end
end
