defmodule Vws.Partitions.HydraulicTest do
  # HYDRAULIC and the PALLET status through the whole path: WC link, SUN_COMM, the partition,
  # the CEC's HPIB, the hydraulic controller, DAQ #2, the plant.
  use ExUnit.Case, async: true

  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Links.Transport
  alias Vws.Test.HydraulicFloor

  doctest Vws.Partitions.Hydraulic
  doctest Vws.Partitions.Hydraulic.Monitor

  test "CLAMP_PALLET: DONE and PALLET CLAMPED; RELEASE_PALLET: DONE and PALLET NOT CLAMPED" do
    %{peer: peer, plant: plant} = HydraulicFloor.start()
    assert HydraulicFloor.await_pallet(peer, &(&1 =~ "PALLET")) == "PALLET NOT CLAMPED"

    assert HydraulicFloor.command(peer, 1, "CLAMP_PALLET") == "DONE"
    # written when the command ended, not a monitor period later
    assert HydraulicFloor.pallet(peer) == "PALLET CLAMPED"
    assert %{force1_n: 5000.0, force2_n: 5000.0} = Plant.snapshot(plant).pallet

    assert HydraulicFloor.command(peer, 2, "RELEASE_PALLET") == "DONE"
    assert HydraulicFloor.pallet(peer) == "PALLET NOT CLAMPED"
    assert %{force1_n: 0.0, force2_n: 0.0, x_switch: false} = Plant.snapshot(plant).pallet
  end

  # The PALLET monitor's read, answered NOT CLAMPED before a CLAMP_PALLET ended and handed back
  # after HYDRAULIC's confirmation wrote PALLET CLAMPED, must not write its older news over it.
  test "a PALLET? answer is not written over what was written since it was asked" do
    ws = "pallet-late-#{System.unique_integer([:positive])}"
    start_supervised!({Vws.CEC.Mailbox.Owner, workstation: ws})
    test = self()

    # an HPIB device 8 that, asked PALLET?, lets the confirmation be written first
    spawn_link(fn ->
      {:ok, _} = Registry.register(Vws.Registry, {ws, {:hpib, 8}}, nil)
      send(test, :registered)

      receive do
        {:"$gen_cast", {Vws.Links.Connection, from, _deadline, {:request, [:pallet?], _}}} ->
          :ok = Vws.CEC.Mailbox.put_device(ws, 10, "PALLET CLAMPED")
          late = %{clamped: false, x: false, y: false, force1_n: 0.0, force2_n: 0.0}
          :gen.reply(from, {:ok, [late]})
          Process.sleep(:infinity)
      end
    end)

    assert_receive :registered
    assert {:ok, %{clamped: false}} = Vws.Partitions.Hydraulic.refresh_pallet(ws, {ws, 8})
    assert {"PALLET CLAMPED", _} = Vws.CEC.Mailbox.get_device(ws, 10)
    refute Map.has_key?(Vws.CEC.Mailbox.readings(ws), :pallet)
  end

  test "the PALLET status follows the pallet without a command (the monitor)" do
    %{peer: peer, plant: plant} = HydraulicFloor.start()
    assert HydraulicFloor.await_pallet(peer, &(&1 =~ "PALLET")) == "PALLET NOT CLAMPED"
    Enum.each(201..204, &(:ok = Plant.close_channel(plant, {:daq2, &1})))

    assert HydraulicFloor.await_pallet(peer, &(&1 == "PALLET CLAMPED")) == "PALLET CLAMPED"
  end

  test "a weak clamp: HYDRAULIC ERROR with the measured force, PALLET NOT CLAMPED" do
    %{peer: peer, plant: plant} = HydraulicFloor.start()
    :ok = Plant.inject_fault(plant, :weak_clamp, where: :pallet, force_n: 1200)

    answer = HydraulicFloor.command(peer, 1, "CLAMP_PALLET")
    assert answer =~ ~r/^ERROR CLAMP 1 FORCE \d+ N BELOW 4000 N$/
    [force] = Regex.run(~r/FORCE (\d+) N/, answer, capture: :all_but_first)
    assert_in_delta String.to_integer(force), 1200, 26
    assert HydraulicFloor.pallet(peer) == "PALLET NOT CLAMPED"
  end

  test "a stuck Y ram valve: ERROR PALLET NOT AGAINST Y STOP" do
    %{peer: peer, plant: plant} = HydraulicFloor.start()
    :ok = Plant.inject_fault(plant, :stuck_valve, actuator: :ram_y_valve)
    assert HydraulicFloor.command(peer, 1, "CLAMP_PALLET") == "ERROR PALLET NOT AGAINST Y STOP"
  end

  test "DAQ #2 not answering: ERROR DAQ #2 NOT ANSWERING, PALLET NO DATA" do
    # the CEC waits on the controller longer than the controller waits on DAQ #2 (300 ms), so
    # that a loaded machine cannot make the controller's answer come too late to be heard
    slow_cec = [status_timeout: 3_000, hydraulic: [options: [request_ms: 3_000]]]
    %{peer: peer, daq2: daq2} = HydraulicFloor.start(hydraulic: slow_cec)
    assert HydraulicFloor.await_pallet(peer, &(&1 =~ "PALLET")) == "PALLET NOT CLAMPED"
    :ok = DAQ.set_fault(daq2, :mute)

    # the PALLET? reads of the monitor share DAQ #2's HPIB with the sequence: whichever request
    # meets the silence first times out, the others find the link reconnecting
    assert HydraulicFloor.command(peer, 1, "CLAMP_PALLET") =~
             ~r/^ERROR DAQ #2 NOT ANSWERING \((NO ANSWER IN 300 MS|TIMED OUT, RECONNECTING)\)$/

    assert HydraulicFloor.await_pallet(peer, &(&1 =~ "NO DATA")) ==
             "NO DATA (HYDRAULIC CONTROLLER CANNOT READ THE PALLET SENSORS)"
  end

  test "a hydraulic controller that does not answer: ERROR ... NOT ANSWERING, PALLET NO DATA" do
    # something that takes the HPIB connection and never answers a line
    {:ok, listener} = Transport.listen("tcp://127.0.0.1:0")
    endpoint = to_string(Transport.listener_endpoint(listener))
    test = self()

    mute =
      spawn_link(fn ->
        Stream.repeatedly(fn -> Transport.accept(listener, :infinity) end)
        |> Enum.each(fn {:ok, conn} -> send(test, {:held, conn}) end)
      end)

    on_exit(fn -> Process.exit(mute, :kill) end)

    %{peer: peer} =
      HydraulicFloor.start(
        endpoint: endpoint,
        hydraulic: [
          hpib: [timeout: 200],
          hydraulic: [options: [request_ms: 200, silence_ms: 600, poll_ms: 20]]
        ]
      )

    assert HydraulicFloor.command(peer, 1, "CLAMP_PALLET") =~
             ~r/^ERROR HYDRAULIC CONTROLLER NOT ANSWERING \((NO ANSWER IN 200 MS|TIMED OUT, RECONNECTING)\)$/

    assert HydraulicFloor.await_pallet(peer, &(&1 =~ "NOT ANSWERING")) ==
             "NO DATA (HYDRAULIC CONTROLLER NOT ANSWERING)"
  end

  test "a hydraulic controller that is gone: ERROR ... NOT CONNECTED, PALLET NO DATA" do
    floor = HydraulicFloor.controller()
    :ok = stop_supervised(floor.controller_id)

    %{peer: peer} =
      HydraulicFloor.workstation(floor,
        hydraulic: [hydraulic: [options: [silence_ms: 300, poll_ms: 20]]]
      )

    assert HydraulicFloor.command(peer, 1, "CLAMP_PALLET") ==
             "ERROR HYDRAULIC CONTROLLER NOT CONNECTED"

    assert HydraulicFloor.await_pallet(peer, &(&1 =~ "NOT CONNECTED")) ==
             "NO DATA (HYDRAULIC CONTROLLER NOT CONNECTED)"
  end

  test "a command on a controller still EXECUTING waits for it, then runs" do
    # the controller runs a CLAMP_PALLET that another CEC sent; its X ram is stuck (DAQ #2 given
    # 1.5 s to answer: its 300 ms default failed one loaded run with NOT ANSWERING)
    floor = HydraulicFloor.controller(controller: [step_timeout_ms: 800, timeout_ms: 1_500])
    :ok = Plant.inject_fault(floor.plant, :stuck_valve, actuator: :ram_x_valve)
    other_cec = HydraulicFloor.hpib(floor.endpoint)
    :ok = Vws.Links.HPIB.write(other_cec, :clamp_pallet)
    assert Vws.Links.HPIB.query(other_cec, :status?) == {:ok, :executing}

    %{peer: peer} = HydraulicFloor.workstation(floor)
    assert HydraulicFloor.command(peer, 1, "CLAMP_PALLET") == "ERROR PALLET NOT AGAINST X STOP"

    # ours was sent once the other had ended, and run: not refused as busy
    assert %{commands: 2, sequences: 2, refused_busy: 0} =
             Vws.Peers.HydraulicController.info(floor.name)
  end

  test "DONE is confirmed on the pallet: a controller restarted mid-command cannot pass for done" do
    floor = HydraulicFloor.controller(controller: [step_timeout_ms: 2_000])
    :ok = Plant.inject_fault(floor.plant, :stuck_valve, actuator: :ram_x_valve)
    %{peer: peer} = HydraulicFloor.workstation(floor)
    task = Task.async(fn -> HydraulicFloor.command(peer, 1, "CLAMP_PALLET") end)

    # the program restarts mid-sequence: it depressurises again and says DONE
    assert Vws.Test.Eventually.eventually(fn ->
             Vws.Peers.HydraulicController.info(floor.name).running == :clamp_pallet
           end)

    [{program, _}] =
      Registry.lookup(Vws.Registry, {{:hydraulic_controller, floor.name}, :program})

    Process.exit(program, :kill)

    assert Task.await(task, 10_000) =~
             ~r/^ERROR PALLET NOT CLAMPED AFTER CLAMP_PALLET \(X=0 Y=0 F1=\d+ N F2=\d+ N\)$/
  end

  test "devices: [hydraulic: …] gives the HPIB device, the PALLET monitor and HYDRAULIC's link" do
    {links, popts} =
      Vws.CEC.Workstation.device_links("w", [hydraulic: "tcp://127.0.0.1:5026"],
        hydraulic: [options: [timeout_ms: 9]]
      )

    assert [%{id: {Vws.Links.HPIB, "w", 8}}, {Vws.Partitions.Hydraulic.Monitor, monitor}] = links
    assert monitor[:link] == {"w", 8}
    assert popts[:hydraulic] == [link: {"w", 8}, options: [timeout_ms: 9]]

    {links, popts} =
      Vws.CEC.Workstation.device_links(
        "w",
        [hydraulic: [endpoint: "loopback:hc", address: 5, status_interval: nil]],
        []
      )

    assert [%{id: {Vws.Links.HPIB, "w", 5}}] = links
    assert popts[:hydraulic] == [link: {"w", 5}]
  end
end
