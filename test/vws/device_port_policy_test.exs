defmodule Vws.DevicePortPolicyTest do
  # Issue 16: the hydraulic controller's HPIB port (and the simulators' ports) let in only their
  # configured peer. The attack that found it: a raw CLAMP_PALLET from any local client clamped
  # the pallet, past the CEC and its interlocks. 127.0.0.2 plays a host that is not the CEC.
  use ExUnit.Case, async: true

  import ExUnit.CaptureLog

  alias Vws.Links.HPIB
  alias Vws.Peers.HydraulicController
  alias Vws.Sim.Plant
  alias Vws.Test.HydraulicFloor

  @stranger {127, 0, 0, 2}

  defp port_of(endpoint), do: Vws.Links.Endpoint.parse!(endpoint).port

  defp raw_from(endpoint, ip) do
    {:ok, s} =
      :gen_tcp.connect({127, 0, 0, 1}, port_of(endpoint), [:binary, active: false, ip: ip])

    s
  end

  test "the hydraulic controller takes commands only from its CEC's address" do
    # (DAQ #2 given 1.5 s to answer: its start-up read missed 300 ms in a loaded CI run)
    %{plant: plant, name: name, endpoint: endpoint} =
      HydraulicFloor.controller(
        controller: [listen: "tcp://127.0.0.1:0", allow: "127.0.0.1", timeout_ms: 1_500]
      )

    log =
      capture_log(fn ->
        s = raw_from(endpoint, @stranger)
        _ = :gen_tcp.send(s, "CLAMP_PALLET\nSTATUS?\n")
        # closed unanswered
        assert {:error, _} = :gen_tcp.recv(s, 0, 5_000)
      end)

    assert log =~ "refused a connection from tcp://127.0.0.2:"
    # nothing ran: no command counted, no valve closed
    assert %{commands: 0, connections: 0} = HydraulicController.info(name)

    for ch <- [201, 202, 203, 204],
        do: assert({:ok, false} == Plant.channel_closed?(plant, {:daq2, ch}))

    # the CEC (127.0.0.1) is served
    cec = HydraulicFloor.hpib(endpoint)
    assert HPIB.query(cec, :status?) == {:ok, :done}
  end

  test "the hydraulic controller will not listen beyond loopback without its CEC's address" do
    plant = start_supervised!({Plant, time_scale: 1000}, id: make_ref())
    daq2 = start_supervised!({Vws.Sim.DAQ, plant: plant, daq: :daq2}, id: make_ref())

    capture_log(fn ->
      assert {:error, {{:shutdown, {:failed_to_start_child, _, {:cannot_listen, why}}}, _}} =
               start_supervised(
                 {HydraulicController,
                  name: "hc-open-#{System.unique_integer([:positive])}",
                  listen: "tcp://0.0.0.0:0",
                  daq2: Vws.Sim.DAQ.endpoint(daq2)},
                 id: make_ref()
               )

      assert why =~ "needs an allow-list"
    end)
  end

  test "a simulated DAQ with an allow-list refuses others" do
    plant = start_supervised!({Plant, time_scale: 1000}, id: make_ref())

    daq =
      start_supervised!({Vws.Sim.DAQ, plant: plant, daq: :daq1, allow: "127.0.0.1"},
        id: make_ref()
      )

    capture_log(fn ->
      s = raw_from(Vws.Sim.DAQ.endpoint(daq), @stranger)
      _ = :gen_tcp.send(s, "*IDN?\n")
      assert {:error, _} = :gen_tcp.recv(s, 0, 5_000)
    end)

    s = raw_from(Vws.Sim.DAQ.endpoint(daq), {127, 0, 0, 1})
    :ok = :gen_tcp.send(s, "*IDN?\n")
    assert {:ok, idn} = :gen_tcp.recv(s, 0, 5_000)
    assert idn =~ "3497"
  end
end
