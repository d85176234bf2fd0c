defmodule Vws.Test.DAQFloor do
  @moduledoc """
  A workstation wired to a simulated plant through a `Vws.Sim.DAQ` on TCP (and to a simulated
  GE-2000), with a WC peer: the whole path of a gripper, fixture or vacuum command, for tests.
  """

  import ExUnit.Callbacks
  import ExUnit.Assertions

  alias Vws.Sim.{Floor, GE2000}
  alias Vws.Test.{WCPeer, Workstation}

  @dnc_link [reply_timeout: 300, wack_delay: 50, backoff_min: 10, backoff_max: 50]

  @doc """
  Starts a `Vws.Sim.Floor` (plant at time scale 1000 unless `:time_scale`, DAQ #1 simulator on
  TCP and, unless `machine: false`, a GE-2000 whose cycle-start input is the DAQ #1 relay), a
  workstation with `devices: [daq1: …, ge2000: …]` and a connected WC peer. The GE-2000 is there
  because the vise may open only while the machine is known to be idle (seed §2.3.8, 3a): its
  status is read every 100 ms. Options: `:time_scale`, `:vws_status` (VWS_STATUS options,
  default a 10 ms poll and stale after 1 s, so that a loaded test machine does not make readings
  stale where a test does not mean it), `:hpib` (device options), `:partitions` (more partition
  options), `:devices` (more devices, e.g. `robot:`), `:machine`. Returns
  `%{ws, plant, daq, ge2000, peer, endpoint}` (the simulators as registered names).
  """
  def start(opts \\ []) do
    ws = "daqfloor-#{System.unique_integer([:positive])}"
    machine? = Keyword.get(opts, :machine, true)

    start_supervised!(
      {Floor,
       workstation: ws,
       time_scale: Keyword.get(opts, :time_scale, 1000),
       seed: 3,
       ge2000: machine? && [link: @dnc_link, programs: %{"000100.PRO" => "O100\nM30\n"}]},
      id: make_ref()
    )

    plant = Floor.plant(ws)
    daq = Floor.daq1(ws)
    endpoint = Floor.daq1_endpoint(ws)

    daq1 = [
      endpoint: endpoint,
      pulse_ms: 20,
      vws_status:
        Keyword.merge([poll_ms: 10, stale_after_ms: 1_000], Keyword.get(opts, :vws_status, [])),
      hpib: Keyword.get(opts, :hpib, [])
    ]

    ge2000 =
      if machine?,
        do: [
          ge2000: [endpoint: GE2000.endpoint(Floor.ge2000(ws)), status_interval: 100] ++ @dnc_link
        ],
        else: []

    %{ws: ^ws, wc: wc} =
      Workstation.start(
        id: ws,
        devices: Keyword.get(opts, :devices, []) ++ [daq1: daq1] ++ ge2000,
        partitions: Keyword.get(opts, :partitions, [])
      )

    {:ok, peer} = WCPeer.connect(wc)

    # the first poll has been answered: tests start from readings, not from NOT READ YET
    assert Vws.Test.Eventually.eventually(fn ->
             match?({:ok, _}, Vws.Partitions.VwsStatus.readings(ws))
           end)

    if machine? do
      assert Vws.Test.Eventually.eventually(fn ->
               match?({"IDLE", _}, Vws.CEC.Mailbox.get_device(ws, 8))
             end)
    end

    %{
      ws: ws,
      plant: plant,
      daq: daq,
      ge2000: machine? && Floor.ge2000(ws),
      peer: peer,
      endpoint: endpoint
    }
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
    prefix = Vws.Codecs.WC.Command.pad4(number)

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
