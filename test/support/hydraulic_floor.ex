defmodule Vws.Test.HydraulicFloor do
  @moduledoc """
  The pallet's whole path for tests: a simulated plant, DAQ #2 on it (`Vws.Sim.DAQ`, `daq: :daq2`),
  the hydraulic controller on DAQ #2, and optionally a workstation with
  `devices: [hydraulic: …]` and a connected WC peer.
  """

  import ExUnit.Callbacks
  import ExUnit.Assertions

  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Test.{WCPeer, Workstation}

  @doc """
  Starts plant (time scale 1000 unless `:time_scale`), DAQ #2 and the hydraulic controller
  (`:controller` options; short step timeouts by default) and waits until it is ready. Options
  `:before_controller` — a function of the plant run before the controller starts.
  Returns `%{plant, daq2, name, controller_id, endpoint}`.
  """
  def controller(opts \\ []) do
    plant =
      start_supervised!(
        {Plant, time_scale: Keyword.get(opts, :time_scale, 1000), seed: 5},
        id: make_ref()
      )

    daq2 = start_supervised!({DAQ, plant: plant, daq: :daq2}, id: make_ref())
    if f = opts[:before_controller], do: f.(plant)
    name = "hc-#{System.unique_integer([:positive])}"

    controller_opts =
      Keyword.merge(
        [name: name, daq2: DAQ.endpoint(daq2), step_timeout_ms: 300, timeout_ms: 300],
        Keyword.get(opts, :controller, [])
      )

    id = make_ref()
    start_supervised!({Vws.Peers.HydraulicController, controller_opts}, id: id)
    assert Vws.Peers.HydraulicController.await_ready(name, 10_000) == :ok

    %{
      plant: plant,
      daq2: daq2,
      name: name,
      controller_id: id,
      endpoint: Vws.Peers.HydraulicController.endpoint(name)
    }
  end

  @doc """
  `controller/1` plus a workstation linked to it and a WC peer. Options: those of
  `controller/1`, `:endpoint` (link the workstation there instead), `:hydraulic` (more
  `devices: [hydraulic: …]` options, e.g. `hydraulic: [options: […]]`).
  Returns the map of `controller/1` with `ws` and `peer`.
  """
  def start(opts \\ []) do
    floor = if opts[:endpoint], do: %{endpoint: opts[:endpoint]}, else: controller(opts)
    workstation(floor, opts)
  end

  @doc "A workstation linked to the controller at `floor.endpoint`, and a WC peer."
  def workstation(floor, opts \\ []) do
    hydraulic =
      Keyword.merge(
        [endpoint: floor.endpoint, status_interval: 50],
        Keyword.get(opts, :hydraulic, [])
      )

    %{ws: ws, wc: wc} = Workstation.start(devices: [hydraulic: hydraulic])
    {:ok, peer} = WCPeer.connect(wc)
    Map.merge(floor, %{ws: ws, peer: peer})
  end

  @doc """
  Sends one hydraulic command over the WC link and waits (up to `timeout` ms) until its status
  is no longer EXECUTING; returns the status text after the command number.
  """
  def command(peer, number, text, timeout \\ 10_000) do
    seq = rem(System.unique_integer([:positive]), 10_000)
    WCPeer.send_string(peer, seq, [{"H", number, text}])
    assert WCPeer.recv_line(peer) =~ "05A"
    prefix = Vws.Codecs.WC.Command.pad4(number)

    answer =
      WCPeer.await_status(
        peer,
        seq,
        "HYDRAULIC_CMD",
        fn answer ->
          String.starts_with?(answer, prefix) and not String.ends_with?(answer, "EXECUTING")
        end,
        timeout
      )

    assert String.starts_with?(answer, prefix), "command #{number} never finished: #{answer}"
    refute String.ends_with?(answer, "EXECUTING"), "command #{number} still executing"
    String.replace_prefix(answer, prefix, "")
  end

  @doc "The PALLET status as the WC reads it."
  def pallet(peer),
    do: WCPeer.status(peer, rem(System.unique_integer([:positive]), 10_000), 1, "PALLET")

  @doc "Polls the PALLET status until `fun.(text)`; returns the last text."
  def await_pallet(peer, fun, timeout \\ 5_000),
    do: WCPeer.await_status(peer, 1, "PALLET", fun, timeout)

  @doc "A CEC end on the controller's HPIB (its own bus), connected."
  def hpib(endpoint, opts \\ []) do
    bus = "cec-#{System.unique_integer([:positive])}"

    start_supervised!(
      {Vws.Links.HPIB, [bus: bus, address: 8, endpoint: endpoint] ++ opts},
      id: make_ref()
    )

    assert Vws.Links.HPIB.await_connected({bus, 8}, 2_000) == :ok
    {bus, 8}
  end

  @doc "Asks STATUS? until it is not EXECUTING; returns it."
  def await_status(device, timeout \\ 10_000) do
    deadline = System.monotonic_time(:millisecond) + timeout

    Stream.repeatedly(fn ->
      {:ok, status} = Vws.Links.HPIB.query(device, :status?)

      cond do
        status != :executing -> status
        System.monotonic_time(:millisecond) > deadline -> :still_executing
        true -> Process.sleep(5) && nil
      end
    end)
    |> Enum.find(& &1)
  end
end
