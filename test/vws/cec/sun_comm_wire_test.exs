defmodule Vws.CEC.SunCommWireTest do
  @moduledoc "SUN_COMM over real links: TCP and a socat pty pair."
  use ExUnit.Case, async: true

  alias Vws.Test.{WCPeer, Workstation}

  # The seed's Table 1 dialogue (steps 1-5, robot and gripper without equipment) on a real link.
  defp table1_dialogue(peer, ws) do
    # BCCs computed by hand (python3: sum(bytes) % 256) for the exact strings of Table 1
    WCPeer.send_line(peer, "*0054*R0009DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)*G0004OPEN*241")
    assert WCPeer.recv_line(peer) == "05A0054" <> bcc("05A0054")

    # both commands end ERROR (no link to the VAL II, none to DAQ #1): waited for, so that a
    # loaded machine does not find the gripper's still EXECUTING when its status is asked below
    assert Vws.Test.Eventually.eventually(fn ->
             match?({9, {:error, _}}, Vws.CEC.Mailbox.command_status(ws, :robot)) and
               match?({4, {:error, _}}, Vws.CEC.Mailbox.command_status(ws, :gripper))
           end)

    WCPeer.send_line(peer, "*0055*S0039ROBOT_CMD*032")

    assert WCPeer.recv_line(peer) ==
             "32S00390009ERROR NO LINK TO VAL II" <> bcc("32S00390009ERROR NO LINK TO VAL II")
  end

  defp bcc(text),
    do:
      text
      |> :binary.bin_to_list()
      |> Enum.sum()
      |> rem(256)
      |> Integer.to_string()
      |> String.pad_leading(3, "0")

  test "over TCP" do
    %{ws: ws} = Workstation.start(wc: "tcp://127.0.0.1:0", sun_comm: [takeover_after: 0])
    # SUN_COMM opens its listener once OK_TO_PROCEED has reached it
    assert Vws.Test.Eventually.eventually(fn -> Vws.CEC.SunComm.listening(ws) != nil end)
    endpoint = Vws.CEC.SunComm.listening(ws)
    assert endpoint.kind == :tcp and endpoint.port > 0
    {:ok, peer} = WCPeer.connect(to_string(endpoint))
    table1_dialogue(peer, ws)

    # a second WC connection takes over (takeover_after 0); the first is closed
    {:ok, peer2} = WCPeer.connect(to_string(endpoint))
    assert WCPeer.status(peer2, 56, 40, "GRIPPER_CMD") == "0004ERROR NO LINK TO DAQ #1"
    assert WCPeer.recv_line(peer, 500) == {:timeout, :closed}
  end

  @tag :tty
  test "over a serial line (a socat pty pair)" do
    pair = Vws.Test.PtyPair.start!()
    %{ws: ws} = Workstation.start(wc: "tty:#{pair.a}?baud=9600")
    assert Vws.Test.Eventually.eventually(fn -> Vws.CEC.SunComm.info(ws).peer != nil end)
    {:ok, peer} = WCPeer.connect("tty:#{pair.b}?baud=9600")
    table1_dialogue(peer, ws)
  end
end
