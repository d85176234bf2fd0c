defmodule Vws.Partitions.RobotE2ETest do
  @moduledoc false
  # The robot command set end to end: a WC peer → SUN_COMM → ROBOT → Vws.Links.VAL → Vws.Links.DDCMP → a
  # byte line (TCP, a socat pty pair, or a fault-placing tap) → the simulated VAL II.
  use ExUnit.Case, async: true

  alias Vws.Sim.VAL2
  alias Vws.Test.{LineTap, WCPeer, Workstation}
  alias Vws.Links.DDCMP.Frame

  defp ack?(line, seq), do: Vws.Codecs.WC.Reply.decode(line) == {:ok, {:ack, seq}}

  defp start_sim(opts) do
    start_supervised!({VAL2, Keyword.put_new(opts, :time_scale, 0.001)}, id: :sim)
  end

  defp start_workstation(robot_endpoint) do
    %{ws: ws, wc: wc} =
      Workstation.start(
        devices: [
          robot: [endpoint: robot_endpoint, ddcmp: [rep_timeout: 200, start_timeout: 200]]
        ],
        partitions: [
          robot: [
            options: [
              command_timeout: 5_000,
              motion_timeout: 10_000,
              work_volumes: %{
                # MV9: a location the CEC knows (clear of every work volume) that the robot
                # controller was never taught, so that the controller's own error comes back
                locations: %{"SAFE" => :safe, "TRAY1" => :tray1, "MV1" => :tray1, "MV9" => :safe}
              }
            ]
          ]
        ]
      )

    {:ok, peer} = WCPeer.connect(wc)
    %{ws: ws, peer: peer}
  end

  defp robot(peer, seq, number, text) do
    WCPeer.send_string(peer, seq, [{"R", number, text}])
    assert ack?(WCPeer.recv_line(peer), seq)
    WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ ~r/^#{pad(number)}(DONE|ERROR)/), 10_000)
  end

  defp pad(n), do: Vws.Codecs.WC.Command.pad4(n)

  # Seed Table 1 (steps 1, 2, 4, 5), then WHERE and an error from the controller.
  defp table1(peer, sim) do
    WCPeer.send_string(peer, 54, [
      {"R", 9, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"},
      {"G", 4, "OPEN"}
    ])

    assert ack?(WCPeer.recv_line(peer), 54)

    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ ~r/^0009(DONE|ERROR)/), 10_000) ==
             "0009DONE"

    assert robot(peer, 57, 10, "DISABLE_TRAY1") == "0010DONE"
    assert robot(peer, 59, 11, "WHERE") == "0011DONE"

    assert WCPeer.status(peer, 60, 1, "WHERE_ROBOT") ==
             "650.0/-577.0/1000.0/0.0/180.0/0.0/-41.6/16.1/254.4/180.0/163.9/138.4"

    assert robot(peer, 61, 12, "DO APPRO TRAY1/100") == "0012DONE"
    assert VAL2.info(sim).world == [650.0, -450.0, 800.0, 0.0, 180.0, 0.0]
    assert robot(peer, 62, 13, "DO MOVE MV9") == "0013ERROR -301 UNDEFINED LOCATION MV9"
    # the arm is still in the tray's volume: the tray stays locked against the MHS (rule 2b)
    assert robot(peer, 63, 14, "RELEASE_TRAY1") == "0014ERROR INTERLOCK ROBOT IN TRAY1 VOLUME"
    assert robot(peer, 64, 15, "DO MOVES SAFE") == "0015DONE"
    assert robot(peer, 65, 16, "RELEASE_TRAY1") == "0016DONE"
    assert %{violations: 0, stale: 0} = VAL2.info(sim)
  end

  test "Table 1 over TCP" do
    sim = start_sim([])
    %{peer: peer} = start_workstation(VAL2.endpoint(sim))
    table1(peer, sim)
  end

  @tag :tty
  test "Table 1 over a socat pty pair" do
    %{a: val_tty, b: cec_tty} = Vws.Test.PtyPair.start!()
    sim = start_sim(endpoint: "tty:#{val_tty}?baud=9600")
    %{peer: peer} = start_workstation("tty:#{cec_tty}?baud=9600")
    table1(peer, sim)
  end

  describe "line faults" do
    setup do
      sim = start_sim([])
      tap = start_supervised!({LineTap, upstream: VAL2.endpoint(sim)})
      Map.merge(%{sim: sim, tap: tap}, start_workstation(LineTap.endpoint(tap)))
    end

    test "a corrupted byte: NAK, retransmission, the command still DONE and run once", %{
      sim: sim,
      tap: tap,
      peer: peer
    } do
      command? = fn _frame, val, _seen -> match?(%{lun: 2, text: "DO MOVE TRAY1"}, val) end
      LineTap.fault(tap, :to_val, command?, :corrupt)

      assert robot(peer, 1, 1, "DO MOVE TRAY1") == "0001DONE"
      log = LineTap.log(tap)

      assert [:corrupted, :passed] ==
               for(
                 {:to_val, %Frame.Data{} = f, fate} <- log,
                 val_text(f) == "DO MOVE TRAY1",
                 do: fate
               )

      assert Enum.any?(log, &match?({:to_cec, %Frame.Control{type: :nak, subtype: 2}, _}, &1))
      assert VAL2.info(sim).commands == ["DO MOVE TRAY1"]
      assert VAL2.info(sim).location == "TRAY1"
    end

    test "a lost ACK: REP recovers and the link goes on", %{sim: sim, tap: tap, peer: peer} do
      reply_to_complete? = fn m ->
        match?(%{lun: 3, function: :reply, qualifier: :motion_complete}, m)
      end

      LineTap.fault(tap, :to_cec, LineTap.acks_val?(reply_to_complete?), :drop)

      assert robot(peer, 1, 1, "DO MOVE TRAY1") == "0001DONE"
      assert Vws.Test.Eventually.eventually(fn -> LineTap.pending(tap) == 0 end)

      assert Vws.Test.Eventually.eventually(fn ->
               Enum.any?(LineTap.log(tap), &match?({:to_val, %Frame.Control{type: :rep}, _}, &1))
             end)

      assert robot(peer, 2, 2, "WHERE") == "0002DONE"
      assert robot(peer, 3, 3, "DO MOVE SAFE") == "0003DONE"
      assert VAL2.info(sim).commands == ["DO MOVE TRAY1", "WHERE", "DO MOVE SAFE"]
    end
  end

  test "a controller restart mid-command: start-up again, the command ends ERROR, not re-sent" do
    sim = start_sim(time_scale: 100.0)
    %{peer: peer} = start_workstation(VAL2.endpoint(sim))

    WCPeer.send_string(peer, 1, [{"R", 1, "DO MOVE TRAY1"}])
    assert ack?(WCPeer.recv_line(peer), 1)
    assert Vws.Test.Eventually.eventually(fn -> VAL2.info(sim).moving end)
    assert WCPeer.status(peer, 2, 39, "ROBOT_CMD") == "0001EXECUTING"

    VAL2.restart(sim)

    assert WCPeer.await_status(peer, 39, "ROBOT_CMD", &(&1 =~ "ERROR")) ==
             "0001ERROR VAL II RESTARTED"

    assert robot(peer, 3, 2, "WHERE") == "0002DONE"
    assert %{commands: ["DO MOVE TRAY1", "WHERE"], violations: 0} = VAL2.info(sim)
  end

  defp val_text(%Frame.Data{data: data}) do
    case Vws.Links.VAL.Message.decode(data) do
      {:ok, m} -> m.text
      _ -> nil
    end
  end
end
