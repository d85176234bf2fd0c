defmodule Vws.Partitions.Monarch.RFC2217Test do
  # MONARCH through a terminal server we did not write: ser2net's RFC 2217 accepter in front
  # of one side of a pty pair, the machine's simulator on the other side. The CEC dials
  # rfc2217://… and sets the port; `stty -F` reads back what the pty got.
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.Links.DNC.Program
  alias Vws.Sim.{GE2000, RS232Control}
  alias Vws.Test.WCPeer
  import Vws.Test.Eventually

  @moduletag :tty
  @moduletag timeout: 180_000

  setup do
    pair = Vws.Test.PtyPair.start!()
    server = Vws.Test.Ser2net.start!(pair.a, pair.dir)
    Map.merge(pair, %{url: "rfc2217://127.0.0.1:#{server.port}"})
  end

  defp workstation(port) do
    %{ws: ws, wc: wc} = Vws.Test.Workstation.start(devices: [ge2000: port])
    link = Workstation.whereis(ws, :ge2000)
    {:ok, peer} = WCPeer.connect(wc)
    %{ws: ws, peer: peer, link: link}
  end

  import Vws.Test.Serial, only: [monarch: 3]

  defp program(bytes, number), do: Vws.Test.Serial.program_lines(bytes, number)

  defp stty(path) do
    {settings, 0} = System.cmd("stty", ["-F", path, "-a"])
    settings
  end

  test "GE-2000 (DNC Level 2) through ser2net: DOWNLOAD_GE, UPLOAD_GE and a drip feed", ctx do
    sim =
      start_supervised!(
        {GE2000,
         endpoint: "tty:#{ctx.b}", cycle_time: 60_000, memory: 2_048, feed_rate: 20_000, tick: 5}
      )

    %{ws: ws, peer: peer, link: link} =
      workstation(
        endpoint: "#{ctx.url}?baud=4800&stop_bits=2&parity=even",
        backoff_min: 10,
        backoff_max: 100
      )

    assert eventually(fn -> Vws.Links.DNC.info(link).state == :idle end, 10_000)
    # the pty took what the CEC asked the terminal server for
    settings = stty(ctx.a)
    assert settings =~ "speed 4800 baud"
    assert settings =~ ~r/(^|\s)cstopb/

    lines = program(3_000, "O4711")
    :ok = Mailbox.put_nc_file(ws, lines)
    assert monarch(peer, 1, "DOWNLOAD_GE") == "0001DONE"
    # DONE: the directory entry has the size and CRC of exactly the bytes sent
    assert "004711.PRO" in GE2000.directory(sim)

    :ok = Mailbox.put_nc_file(ws, [])
    assert monarch(peer, 2, "UPLOAD_GE(004711.PRO)") == "0002DONE"
    assert Mailbox.nc_up(ws) == lines

    drip = program(6_000, "O4712")
    :ok = Mailbox.put_nc_file(ws, drip)
    assert monarch(peer, 3, "DRIP_FEED") == "0003DONE"
    assert eventually(fn -> GE2000.drip(sim).state == :done end, 30_000)
    assert GE2000.drip(sim).crc == Vws.Codecs.CRC16.compute(Program.to_text(drip))
  end

  test "a plain RS-232 control through ser2net: download read back, and a drip feed under XON/XOFF",
       ctx do
    sim =
      start_supervised!(
        # XOFF at 256 bytes, 768 more for what is in flight when it is sent (800 ms at 9600 Bd):
        # 256 of 512 overflowed once on a loaded machine and the read-back differed
        {
          RS232Control,
          # it says XOFF whatever the pace of a loaded host's sender
          tty: "tty:#{ctx.b}",
          buffer: 1_024,
          high: 256,
          rate: 500,
          punch_after_load: true,
          busy_until_xoff: true
        }
      )

    # flow=none on the server: the link does XON/XOFF itself, so it sees them and bounds the wait
    %{ws: ws, peer: peer, link: link} =
      workstation(
        endpoint: "#{ctx.url}?baud=9600&flow=none",
        profile: "rs232-xonxoff",
        backoff_min: 10,
        backoff_max: 100
      )

    assert eventually(fn -> Vws.Links.RS232.info(link).state == :idle end, 10_000)
    assert stty(ctx.a) =~ "speed 9600 baud"

    lines = program(3_000, "O4711")
    :ok = Mailbox.put_nc_file(ws, lines)
    assert monarch(peer, 1, "DOWNLOAD_GE") == "0001DONE"
    assert RS232Control.info(sim).programs["004711.PRO"] == Program.to_text(lines)

    # a control slower than the line (500 characters a second against 960): it must say XOFF
    drip = program(3_000, "O4712")
    :ok = Mailbox.put_nc_file(ws, drip)
    assert monarch(peer, 2, "DRIP_FEED") == "0002DONE"
    assert eventually(fn -> RS232Control.info(sim).last == Program.to_text(drip) end)
    info = RS232Control.info(sim)
    assert info.xoffs > 0 and info.dropped == 0, inspect(Map.drop(info, [:programs, :last]))
  end
end
