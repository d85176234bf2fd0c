defmodule Vws.Partitions.Monarch.MonitorTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.Mailbox
  alias Vws.Partitions.Monarch.Monitor
  alias Vws.Sim.GE2000
  import Vws.Test.Eventually

  doctest Monitor

  test "the MONARCH status follows the machine without a command from the WC" do
    sim =
      start_supervised!({GE2000, cycle_time: 60_000, programs: %{"000100.PRO" => "O100\nM30\n"}})

    %{ws: ws} =
      Vws.Test.Workstation.start(
        devices: [ge2000: [endpoint: GE2000.endpoint(sim), status_interval: 20]]
      )

    monarch = fn -> elem(Mailbox.get_device(ws, 8), 0) end
    assert eventually(fn -> monarch.() == "IDLE" end)

    # a cycle started at the control panel
    GE2000.put_program(sim, "000100.PRO", "O100\nM30\n")
    link = Vws.CEC.Workstation.whereis(ws, :ge2000)

    {:ok, []} =
      Vws.Links.DNC.request(
        link,
        %Vws.Links.DNC.Frame.Command{operation: :remote_control, text: "000100"},
        []
      )

    assert eventually(fn -> GE2000.state(sim).selected == "000100" end)
    GE2000.cycle_start(sim)
    assert eventually(fn -> monarch.() == "ACTIVE" end)
    GE2000.end_cycle(sim)
    assert eventually(fn -> monarch.() == "IDLE" end)
  end

  test "status_interval nil: a monitor that reads nothing, there to own the link (programs from the machine)" do
    {links, partitions} =
      Vws.CEC.Workstation.device_links(
        "w",
        [ge2000: [endpoint: "tcp://h:1", status_interval: nil]],
        []
      )

    assert [{Vws.Links.DNC, opts}, {Vws.Partitions.Monarch.Monitor, monitor}] = links
    assert opts[:endpoint] == "tcp://h:1"
    assert monitor[:interval] == nil
    assert partitions[:monarch][:link] == Vws.Names.via("w", :ge2000)
  end
end
