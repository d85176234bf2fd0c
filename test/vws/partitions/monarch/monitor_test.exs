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

  # A status read answered IDLE an instant before a drip feed's first block, and handed back after
  # the feed said ACTIVE: the read must not make MONARCH IDLE while the program runs (CI saw an
  # IDLE sample in DripFeedTest "MONARCH says ACTIVE …" on a loaded host: the reading process
  # wrote its old answer after the feed's ACTIVE).
  test "a status read answered before a drip feed began is not written over the feed's ACTIVE" do
    %{ws: ws} = Vws.Test.Workstation.start(devices: [])
    test = self()

    # a link that, asked for the status, tells its owner a drip feed runs, then answers IDLE
    link =
      spawn_link(fn ->
        fake_link = fn fake_link, owner ->
          receive do
            {:"$gen_call", from, {:set_owner, pid}} ->
              :gen.reply(from, :ok)
              fake_link.(fake_link, pid)

            {:"$gen_cast", {Vws.Links.Connection, from, _deadline, {:request, command, []}}}
            when command.operation == :status ->
              progress = %{operation: :download_execute, ended: false, program: "004711.PRO"}
              send(owner, {:dnc, self(), {:progress, progress}})
              # the feed's ACTIVE is in the mailbox before the read's IDLE is handed back
              assert eventually(fn -> elem(Mailbox.get_device(ws, 8), 0) == "ACTIVE" end)
              idle = Vws.Links.DNC.Report.status(%{state: :idle, program: "000000", alarm: 0})
              :gen.reply(from, {:ok, [idle]})
              send(test, :answered)
              fake_link.(fake_link, owner)
          end
        end

        fake_link.(fake_link, nil)
      end)

    monitor = start_supervised!({Monitor, workstation: ws, link: link, interval: 60_000})
    assert_receive :answered, 5_000

    # the monitor has handled the read's answer (the next read is a minute away)
    assert eventually(fn -> :sys.get_state(monitor).reading == nil end)
    assert {"ACTIVE", _} = Mailbox.get_device(ws, 8)
    assert {%{state: :active, program: "004711"}, _} = Mailbox.readings(ws).monarch
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
