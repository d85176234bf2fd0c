defmodule Vws.Partitions.RobotTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Interlock, Mailbox}
  alias Vws.Partitions.Robot
  alias Vws.Test.VALPeer
  alias Vws.Links.VAL.Message
  import Vws.Test.Eventually

  doctest Robot

  # ROBOT on a Vws.Links.VAL: the test plays the VAL II through a DDCMP peer of its own (`link`).
  setup context do
    ws = "robot-#{System.unique_integer([:positive])}"
    test = self()
    {:ok, link} = VALPeer.start_link()

    options =
      Map.get(context, :options, []) ++
        [
          command_timeout: 2_000,
          motion_timeout: 2_000,
          interlock: [timeout: 300, retry_ms: 50],
          # MV9: known to the CEC (clear of every work volume), never taught to the controller
          work_volumes: %{
            locations: %{"SAFE" => :safe, "TRAY1" => :tray1, "MV1" => :tray1, "MV9" => :safe}
          }
        ]

    options =
      if context[:tray_lock],
        do:
          [
            tray_lock: fn n, action ->
              send(test, {:tray_lock, n, action}) && context[:tray_lock]
            end
          ] ++ options,
        else: options

    start_supervised!(
      {Vws.CEC.Workstation,
       id: ws,
       wc: nil,
       devices: [robot: [endpoint: VALPeer.endpoint(link)]],
       partitions: [robot: [options: options]]}
    )

    :ok = VALPeer.up(link)
    %{ws: ws, link: link}
  end

  defp run(ws, number, text) do
    :ok = Vws.CEC.Partition.dispatch(ws, :robot, number, text)
  end

  defp status(ws), do: Mailbox.command_status(ws, :robot)

  defp finished(ws, number) do
    assert eventually(fn -> Mailbox.in_flight(ws, :robot) == nil end)
    {^number, status} = status(ws)
    status
  end

  defp deliver(link, lun, function, qualifier, text) do
    {:ok, m} = Message.new(lun, function, qualifier, text)
    VALPeer.deliver(link, Message.encode(m))
  end

  defp prompt(link), do: deliver(link, 2, :read, 0, ".")

  defp sent(link) do
    assert_receive {:val_peer, ^link, {:sent, bin}}, 2_000
    {:ok, m} = Message.decode(bin)
    {m.lun, m.function, m.qualifier, m.text}
  end

  # the monitor's side of one command: prompt, take the command, answer, take the reply
  defp answer(link, expected, response) do
    prompt(link)
    assert sent(link) == {2, :write, 0, expected}
    deliver(link, 2, :write, 0, response)
    assert sent(link) == {2, :reply, 0, ""}
  end

  defp motion_complete(link) do
    deliver(link, 3, :write, :motion_begin, "MOTION BEGIN")
    assert sent(link) == {3, :reply, :motion_begin, ""}
    deliver(link, 3, :write, :motion_complete, "MOTION COMPLETE")
    assert sent(link) == {3, :reply, :motion_complete, ""}
  end

  test "WHERE writes WHERE_ROBOT: six world coordinates and six joint values", %{
    ws: ws,
    link: link
  } do
    run(ws, 1, "WHERE")

    answer(
      link,
      "WHERE",
      "0\r\n  X  Y  Z  O  A  T\r\n  650.00 -577.00 1000.00 0.00 180.00 0.00\r\n" <>
        "  JT1 JT2 JT3 JT4 JT5 JT6\r\n  -41.60 16.05 254.39 180.00 163.95 138.40"
    )

    assert finished(ws, 1) == :done

    assert {"650.0/-577.0/1000.0/0.0/180.0/0.0/-41.6/16.1/254.4/180.0/163.9/138.4", _} =
             Mailbox.get_device(ws, 9)

    assert Vws.CEC.SunComm.Status.answer(ws, "WHERE_ROBOT") =~ ~r{^650\.0/-577\.0/}
  end

  test "a motion from Table 1 goes in VAL II syntax and is DONE at MOTION COMPLETE", %{
    ws: ws,
    link: link
  } do
    run(ws, 9, "DO MOVE MV1:TRANS(63.5/0/0/90/-90/0)")
    answer(link, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)", "0")
    assert status(ws) == {9, :executing}
    motion_complete(link)
    assert finished(ws, 9) == :done

    run(ws, 10, "DO APPROS TRAY1/50")
    answer(link, "DO APPROS TRAY1, 50", "0")
    motion_complete(link)
    assert finished(ws, 10) == :done

    run(ws, 11, "SPEED 30")
    answer(link, "SPEED 30", "0")
    assert finished(ws, 11) == :done
  end

  test "a numbered error from the controller surfaces as ERROR <code> <text>", %{
    ws: ws,
    link: link
  } do
    run(ws, 12, "DO MOVE MV9")
    answer(link, "DO MOVE MV9", "-301 UNDEFINED LOCATION MV9")
    assert finished(ws, 12) == {:error, "-301 UNDEFINED LOCATION MV9"}

    assert Vws.CEC.SunComm.Status.answer(ws, "ROBOT_CMD") ==
             "0012ERROR -301 UNDEFINED LOCATION MV9"
  end

  test "the link going down mid-motion ends the command ERROR, and it is not sent again", %{
    ws: ws,
    link: link
  } do
    run(ws, 13, "DO MOVE SAFE")
    answer(link, "DO MOVE SAFE", "0")
    VALPeer.down(link, :too_many_failures)
    assert finished(ws, 13) == {:error, "VAL II LINK DOWN"}
    VALPeer.up(link)
    prompt(link)
    refute_receive {:val_peer, ^link, {:sent, _}}, 100
  end

  test "DISABLE_TRAYn/RELEASE_TRAYn take and give up the tray's lease in the mailbox", %{
    ws: ws
  } do
    run(ws, 20, "DISABLE_TRAY1")
    assert finished(ws, 20) == :done
    assert Interlock.holder(ws, :tray1) == :robot

    assert [%{volume: :tray1, holder: :robot, reasons: [:disabled]}] = Interlock.held(ws)

    # taking it again is harmless
    run(ws, 22, "DISABLE_TRAY1")
    assert finished(ws, 22) == :done

    run(ws, 23, "RELEASE_TRAY1")
    assert finished(ws, 23) == :done
    assert Interlock.holder(ws, :tray1) == nil

    # a tray the material-handling system holds: re-tried, then refused; its lease is not ours
    :ok = Interlock.acquire(ws, :tray2, :mhs, 0)
    run(ws, 25, "DISABLE_TRAY2")
    assert finished(ws, 25) == {:error, "INTERLOCK TRAY2 HELD BY MHS"}
    run(ws, 26, "RELEASE_TRAY2")
    assert finished(ws, 26) == :done
    assert Interlock.holder(ws, :tray2) == :mhs
  end

  test "a motion into a tray's volume takes it for the arm; leaving gives it up", %{
    ws: ws,
    link: link
  } do
    run(ws, 27, "DO APPROS TRAY1/50")
    answer(link, "DO APPROS TRAY1, 50", "0")
    assert Interlock.holds?(ws, :tray1, :robot, :inside)
    motion_complete(link)
    assert finished(ws, 27) == :done

    # the arm is there: the tray may not be released to the MHS
    run(ws, 28, "RELEASE_TRAY1")
    assert finished(ws, 28) == {:error, "INTERLOCK ROBOT IN TRAY1 VOLUME"}
    assert {:error, "INTERLOCK TRAY1 HELD BY ROBOT"} = Interlock.acquire(ws, :tray1, :mhs, 0)

    run(ws, 29, "DO MOVE SAFE")
    answer(link, "DO MOVE SAFE", "0")
    motion_complete(link)
    assert finished(ws, 29) == :done
    assert Interlock.held(ws) == []
  end

  test "a location the CEC has no work volume for never reaches the robot", %{
    ws: ws,
    link: link
  } do
    run(ws, 31, "DO MOVE NOWHERE")
    assert finished(ws, 31) == {:error, "INTERLOCK NO WORK VOLUME FOR NOWHERE"}
    prompt(link)
    refute_receive {:val_peer, ^link, {:sent, _}}, 100
  end

  @tag tray_lock: :ok
  test "the tray-lock seam is called when the lease is taken and before it is given up", %{
    ws: ws
  } do
    run(ws, 30, "DISABLE_TRAY2")
    assert finished(ws, 30) == :done
    assert_received {:tray_lock, 2, :lock}
    run(ws, 31, "RELEASE_TRAY2")
    assert finished(ws, 31) == :done
    assert_received {:tray_lock, 2, :release}
  end

  @tag tray_lock: {:error, "relay stuck"}
  test "a tray lock that fails gives the lease back", %{ws: ws} do
    run(ws, 33, "DISABLE_TRAY1")
    assert finished(ws, 33) == {:error, "TRAY 1 LOCK FAILED RELAY STUCK"}
    assert Interlock.holder(ws, :tray1) == nil
  end

  @tag options: [reinit: true]
  test "re-initialisation between commands restarts the link after each one", %{
    ws: ws,
    link: link
  } do
    run(ws, 40, "SPEED 20")
    answer(link, "SPEED 20", "0")
    assert finished(ws, 40) == :done
    assert_receive {:val_peer, ^link, :restart}

    # the next command waits for the start-up and a fresh prompt
    run(ws, 41, "WHERE")
    prompt(link)
    refute_receive {:val_peer, ^link, {:sent, _}}, 100
    VALPeer.up(link)
    answer(link, "WHERE", "0 1 2 3 4 5 6 7 8 9 10 11 12")
    assert finished(ws, 41) == :done
    assert_receive {:val_peer, ^link, :restart}
  end

  test "a WHERE response that is not 12 numbers ends ERROR", %{ws: ws, link: link} do
    run(ws, 50, "WHERE")
    answer(link, "WHERE", "0 1 2 3")
    assert finished(ws, 50) == {:error, "VAL II BAD WHERE RESPONSE"}
  end
end
