defmodule Vws.CEC.Cell.ConnectionTest do
  use ExUnit.Case, async: true

  alias Vws.Links.{Endpoint, Transport}
  alias Vws.Test.{ObedientPartition, WCPeer, Workstation}

  doctest Vws.CEC.Cell.Connection

  test "cell:<id> parses and prints back" do
    assert Endpoint.parse("cell:VWS-1") == {:ok, %Endpoint{kind: :cell, name: "VWS-1"}}
    assert to_string(Endpoint.parse!("cell:VWS-1")) == "cell:VWS-1"
    assert to_string(%Endpoint{kind: :cell, name: {:ws, 1}}) == "cell:{:ws, 1}"
    assert {:error, %{reason: :bad_name}} = Endpoint.parse("cell:")
    assert {:error, %{reason: :bad_name}} = Endpoint.parse("cell:a b")
  end

  test "a cell endpoint cannot listen; an unknown workstation cannot be reached" do
    assert Transport.listen("cell:x") ==
             {:error, %Vws.Links.Transport.Error{reason: :not_listenable}}

    assert Vws.CEC.Cell.connect("cell:no-such-workstation") ==
             {:error, %Vws.Links.Transport.Error{reason: :not_found}}

    # the transports know nothing of the cell: resolving is done above them
    assert Transport.connect("cell:no-such-workstation") ==
             {:error, %Vws.Links.Transport.Error{reason: :not_resolved}}
  end

  test "the bytes are those of a direct link, both ways" do
    %{ws: ws, wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
    {:ok, direct} = WCPeer.connect(wc)
    status = WCPeer.string(1, [{"S", 1, "ROBOT_CMD"}])
    :ok = WCPeer.send_raw(direct, status)
    answer = WCPeer.recv_line(direct)
    WCPeer.close(direct)

    {:ok, via_cell} = WCPeer.connect("cell:#{ws}")
    :ok = WCPeer.send_raw(via_cell, status)
    assert WCPeer.recv_line(via_cell) == answer
    assert answer =~ ~r/^\d\dS00010000NONE\d{3}$/
  end

  test "a SUN_COMM on TCP is dialled over TCP" do
    %{ws: ws} =
      Workstation.start(wc: "tcp://127.0.0.1:0", partitions: ObedientPartition.partitions())

    {:ok, client} = Vws.Peers.WC.Client.connect("cell:#{ws}")
    assert {:ok, "0000NONE"} = Vws.Peers.WC.Client.status(client, "ROBOT_CMD")

    assert Vws.Peers.WC.Client.info(client).peer =~
             ~r/^cell:#{ws} on .* \(tcp:\/\/127\.0\.0\.1:\d+\)$/
  end

  test "the client side hears the close when the workstation goes away" do
    %{ws: ws} = Workstation.start(partitions: ObedientPartition.partitions())
    {:ok, conn} = Vws.CEC.Cell.connect("cell:#{ws}")
    :ok = Transport.activate(conn)
    :ok = stop_supervised({Vws.CEC.Workstation, ws})
    assert_receive msg
    assert Transport.handle_message(conn, msg) == :closed
  end
end
