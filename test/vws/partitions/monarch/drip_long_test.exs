defmodule Vws.Partitions.Monarch.DripLongTest do
  # A library program longer than the GE-2000 can store (issue 27 item 5: "long programs can
  # come from the library"), end to end: the WC (a raw WC peer) → SUN_COMM → MONARCH → the
  # program library → DNC link → the simulated GE-2000's 8 KiB block buffer, at a fast machine.
  use ExUnit.Case, async: true

  alias Vws.CEC.Library
  alias Vws.Links.DNC.Program
  alias Vws.Sim.GE2000
  alias Vws.Test.{MonarchWC, WCPeer}
  import Vws.Test.Eventually

  @memory 8_192

  setup do
    MonarchWC.start("vws-drip-long",
      sim: [memory: @memory, feed_rate: 5_000_000, tick: 5],
      partitions: [monarch: [options: [interlock: [timeout: 300, retry_ms: 50]]]]
    )
  end

  @tag timeout: 180_000
  test "a 1.5 MB library program is drip-fed byte for byte through the 8 KiB buffer; " <>
         "DOWNLOAD_GE of the same version ends ERROR, nothing sent",
       %{ws: ws, peer: peer, sim: sim} do
    text = MonarchWC.long_program(88)
    assert byte_size(text) == 1_500_024
    assert byte_size(text) > Program.max_stored_bytes()
    {:ok, v} = Library.store(ws, "88", text, source: "iex")

    # stored on the machine: refused before a byte is sent
    too_large = "ERROR PROGRAM TOO LARGE 1500024 BYTES (LIMIT 999999)"
    assert WCPeer.monarch(peer, 1, "DOWNLOAD_GE(000088.PRO)") == too_large
    assert WCPeer.monarch(peer, 2, "DOWNLOAD_GE(000088.PRO/1/FORCE)") == too_large
    assert GE2000.state(sim).downloads == 0
    assert GE2000.directory(sim) == []

    # drip-fed: the machine keeps none of it, so it goes
    assert WCPeer.monarch(peer, 3, "DRIP_FEED(000088.PRO)", 150_000) == "DONE"
    assert eventually(fn -> GE2000.drip(sim).state == :done end, 30_000)
    drip = GE2000.drip(sim)
    assert {drip.received, drip.ran} == {byte_size(text), byte_size(text)}
    assert drip.sha256 == v.digest
    assert drip.max_fill <= @memory
    assert GE2000.directory(sim) == []

    # the transfer history says what went: the whole version, DONE
    {:ok, %{records: [last | _]}} = Library.history(ws)
    assert {last.program, last.bytes, last.result} == {"000088.PRO", 1_500_024, "DONE"}

    # restarted near its end (issue 27 item 2): what runs is the restart of the long program
    {:ok, lines, 1, _preamble} = Vws.Partitions.Monarch.restart(ws, "000088.PRO", :latest, 80_000)
    assert WCPeer.monarch(peer, 4, "DRIP_FEED(000088.PRO/N80000)", 150_000) == "DONE"
    restarted = Program.to_text(lines)
    assert restarted =~ "\n" <> Enum.at(Program.from_text(text), 79_999) <> "\n"
    assert eventually(fn -> GE2000.drip(sim).state == :done end, 30_000)
    drip = GE2000.drip(sim)
    assert drip.received == byte_size(restarted)
    assert drip.sha256 == Library.digest(restarted)
  end
end
