defmodule Vws.Test.DAQFloor do
  @moduledoc """
  A workstation wired to a simulated plant through a `Vws.Sim.DAQ` on TCP, with a WC peer: the
  whole path of a gripper, fixture or vacuum command, for tests.
  """

  import ExUnit.Callbacks
  import ExUnit.Assertions

  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Test.{WCPeer, Workstation}

  @doc """
  Starts plant (time scale 1000 unless `:time_scale`), DAQ #1 simulator on TCP, a workstation
  with `devices: [daq1: …]` and a connected WC peer. Options: `:time_scale`, `:vws_status`
  (VWS_STATUS options, default a 10 ms poll and stale after 1 s, so that a
  loaded test machine does not make readings stale where a test does not mean it), `:hpib` (device options), `:partitions`
  (more partition options), `:devices` (more devices, e.g. `robot:`). Returns `%{ws, plant, daq, peer, endpoint}`.
  """
  def start(opts \\ []) do
    plant =
      start_supervised!(
        {Plant, time_scale: Keyword.get(opts, :time_scale, 1000), seed: 3},
        id: make_ref()
      )

    daq = start_supervised!({DAQ, plant: plant}, id: make_ref())
    endpoint = DAQ.endpoint(daq)

    daq1 = [
      endpoint: endpoint,
      vws_status:
        Keyword.merge([poll_ms: 10, stale_after_ms: 1_000], Keyword.get(opts, :vws_status, [])),
      hpib: Keyword.get(opts, :hpib, [])
    ]

    %{ws: ws, wc: wc} =
      Workstation.start(
        devices: Keyword.get(opts, :devices, []) ++ [daq1: daq1],
        partitions: Keyword.get(opts, :partitions, [])
      )

    {:ok, peer} = WCPeer.connect(wc)

    # the first poll has been answered: tests start from readings, not from NOT READ YET
    assert Vws.Test.Eventually.eventually(fn ->
             match?({:ok, _}, Vws.Partitions.VwsStatus.readings(ws))
           end)

    %{ws: ws, plant: plant, daq: daq, peer: peer, endpoint: endpoint}
  end

  @set_names %{
    "G" => "GRIPPER_CMD",
    "F" => "FIXTURE_CMD",
    "V" => "VACUUM_CMD",
    "R" => "ROBOT_CMD",
    "M" => "MONARCH_CMD"
  }

  @doc """
  Sends one command over the WC link and waits (up to `timeout` ms) until its status is no
  longer EXECUTING; returns the status text after the command number (`"DONE"`, `"ERROR …"`).
  """
  def command(peer, letter, number, text, timeout \\ 10_000) do
    seq = rem(System.unique_integer([:positive]), 10_000)
    WCPeer.send_string(peer, seq, [{letter, number, text}])
    assert WCPeer.recv_line(peer) =~ "05A"
    name = Map.fetch!(@set_names, letter)
    prefix = number |> Integer.to_string() |> String.pad_leading(4, "0")

    answer =
      WCPeer.await_status(
        peer,
        seq,
        name,
        fn answer ->
          String.starts_with?(answer, prefix) and not String.ends_with?(answer, "EXECUTING")
        end,
        timeout
      )

    assert String.starts_with?(answer, prefix), "command #{number} never finished: #{answer}"
    refute String.ends_with?(answer, "EXECUTING"), "command #{number} still executing"
    String.replace_prefix(answer, prefix, "")
  end

  @doc "A device status (`GRIPPER`, `VISE`, …) as the WC reads it."
  def status(peer, name) do
    WCPeer.status(peer, rem(System.unique_integer([:positive]), 10_000), 1, name)
  end

  @doc "Polls a device status until `fun.(text)`; returns the last text."
  def await_status(peer, name, fun, timeout \\ 5_000),
    do: WCPeer.await_status(peer, 1, name, fun, timeout)
end
