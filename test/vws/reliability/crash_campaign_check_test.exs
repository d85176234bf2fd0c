defmodule Vws.Reliability.CrashCampaignCheckTest do
  # The crash campaign's judge (Vws.Test.CrashCampaign.check/2) on made-up events: a relay write
  # that ran twice is the command run twice, unless the bus of that very DAQ sent the write again.
  use ExUnit.Case, async: true

  alias Vws.Test.CrashCampaign

  # CLAMP_PALLET: the hydraulic controller closes ram X's valve, on DAQ #2 (channel 201 there,
  # as DAQ #1 has a channel 201 of its own)
  defp events(retry_on) do
    table = :ets.new(:events, [:ordered_set, :public])
    key = fn t -> {t, t} end
    id = {:hydraulic, 3}

    rows =
      [
        {key.(1), :dispatched, id, "CLAMP_PALLET"},
        {key.(2), :executed, {:relay, :ram_x_valve, :close}, {:daq2, 201}},
        {key.(4), :executed, {:relay, :ram_x_valve, :close}, {:daq2, 201}},
        {key.(5), :finished, id, :done}
      ] ++
        for daq <- List.wrap(retry_on),
            do: {key.(3), :retried, [{:rout_clos, [201]}, {:rout_clos?, [201]}], daq}

    :ets.insert(table, rows)
    table
  end

  test "the recorder keeps each execution's DAQ, and each bus try's DAQ by its bus" do
    ws = "recorder-#{System.unique_integer([:positive])}"
    table = CrashCampaign.record(ws)

    {daq2_bus, _} =
      Vws.Peers.HydraulicController.daq2_device(Vws.Sim.Floor.hydraulic_controller(ws))

    write = [rout_clos: [201], rout_clos?: [201, 202]]

    Vws.Telemetry.execute([:vws, :sim, :plant, :actuator], %{count: 1}, %{
      workstation: ws,
      daq: :daq2,
      channel: 201,
      signal: :ram_x_valve,
      action: :close
    })

    for bus <- [daq2_bus, ws, "another cell"] do
      Vws.Telemetry.execute([:vws, :hpib, :retry], %{count: 1}, %{
        bus: bus,
        address: 9,
        commands: write
      })
    end

    # the controller's corrections of DAQ #2's relays, by its device; another cell's are not kept
    for device <- [{daq2_bus, 9}, {{:hydraulic_controller, "another cell"}, 9}] do
      Vws.Telemetry.execute([:vws, :hydraulic_controller, :relay_corrected], %{count: 1}, %{
        device: device
      })
    end

    assert for({_key, what, a, b} <- :ets.tab2list(table), do: {what, a, b}) == [
             {:executed, {:relay, :ram_x_valve, :close}, {:daq2, 201}},
             {:retried, write, :daq2},
             {:retried, write, :daq1},
             {:corrected, {daq2_bus, 9}, :daq2}
           ]
  end

  test "a write DAQ #2's bus sent again is the bus's try, not the command run twice" do
    assert %{bus_retried: 1, executed: 2} = CrashCampaign.check(events(:daq2), [])
  end

  test "without that try, or with a try of DAQ #1's channel of the same number, it ran twice" do
    for retry_on <- [nil, :daq1] do
      error =
        assert_raise ExUnit.AssertionError, fn -> CrashCampaign.check(events(retry_on), []) end

      assert error.message =~ "{:hydraulic, 3} ran 2 times"
    end
  end

  test "a failure's story names the hydraulic controller's relay corrections among what bears on it" do
    table = events(nil)
    :ets.insert(table, {{3, 3}, :corrected, {{:hydraulic_controller, :x}, 9}, :daq2})
    error = assert_raise ExUnit.AssertionError, fn -> CrashCampaign.check(table, []) end
    [bears, _everything] = String.split(error.message, "every event around it")
    assert bears =~ ~r/what bears on it:(.|\n)*corrected \{\{:hydraulic_controller, :x\}, 9\}/
  end
end
