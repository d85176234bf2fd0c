defmodule Vws.CycleRFC2217Test do
  @moduledoc """
  The shipped machining cycle with the workstation's GE-2000 reached through a terminal server we
  did not write (issue 28, item 3): ser2net's RFC 2217 accepter in front of one side of a pty
  pair, the GE-2000 simulator on the other side, the rest of the floor as the demo has it. The
  cycle's download, program select, cycle start and the status polls all cross ser2net; `stty -F`
  then reads back what the pty got from the CEC's COM-PORT-OPTION settings.
  """
  use ExUnit.Case, async: true

  alias Vws.Peers.WC.{Client, Runner, Script}
  alias Vws.Peers.WC.Runner.Summary
  alias Vws.Sim.{Floor, GE2000, Plant}

  @moduletag :tty
  @moduletag timeout: 240_000

  test "machining_cycle.vws through ser2net: every command DONE, every physical check true, " <>
         "the part back in tray #1, and the pty set as the CEC asked" do
    pair = Vws.Test.PtyPair.start!()
    server = Vws.Test.Ser2net.start!(pair.a, pair.dir)
    # the pty does not pace (any speed is as fast), so the fastest termios speed is as good as
    # any; two stop bits because a Linux pty keeps them (it forces cs8 -parenb)
    url = "rfc2217://127.0.0.1:#{server.port}?baud=115200&stop_bits=2"

    id = "cycle-2217-#{System.unique_integer([:positive])}"
    on_exit(fn -> Vws.CEC.Workstation.stop(id) end)

    {:ok, floor} =
      Vws.Ops.Demo.start_shop_floor(
        id: id,
        wc: "loopback:#{id}",
        time_scale: 50,
        ge2000: [endpoint: "tty:#{pair.b}"],
        devices: [ge2000: [endpoint: url, backoff_min: 10, backoff_max: 100]]
      )

    # the simulator is on the pty, and the workstation's link dials the terminal server
    assert GE2000.endpoint(Floor.ge2000(id)) == "tty:#{pair.b}"
    link = Vws.CEC.Workstation.whereis(id, :ge2000)
    assert to_string(Vws.Links.DNC.info(link).endpoint) =~ "rfc2217://127.0.0.1:#{server.port}"

    {:ok, client} = Client.connect(floor.wc)
    {:ok, script} = Script.parse_file("priv/sims/machining_cycle.vws")
    summary = Runner.run(client, script, poll_interval: 5)

    assert Summary.completed?(summary), "stopped: #{inspect(summary.stopped)}"
    parts = for {where, part} <- Plant.snapshot(Floor.plant(id)).parts, part, do: where
    assert parts == [:tray1]
    assert Vws.CEC.Interlock.held(id) == []
    assert Plant.collisions(Floor.plant(id)) == []

    # the program the cycle downloaded is on the machine, filed whole, as the shipped file reads
    assert "001234.PRO" in GE2000.directory(Floor.ge2000(id))

    {settings, 0} = System.cmd("stty", ["-F", pair.a, "-a"])
    assert settings =~ "speed 115200 baud"
    assert settings =~ ~r/(^|\s)cstopb/
  end
end
