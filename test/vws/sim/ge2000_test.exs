defmodule Vws.Sim.GE2000Test do
  # The simulated GE-2000 seen from a bare CEC link: what it files, selects, deletes and reports.
  use ExUnit.Case, async: true

  alias Vws.Links.DNC
  alias Vws.Links.DNC.Frame.Command
  alias Vws.Links.DNC.Report
  alias Vws.Sim.GE2000
  import Vws.Test.Eventually

  doctest GE2000

  setup do
    test = self()

    sim =
      start_supervised!(
        {GE2000,
         programs: %{"000100.PRO" => "O100\nM30\n"},
         cycle_time: 60_000,
         plant: &send(test, {:plant, &1})}
      )

    cec = start_supervised!({DNC, endpoint: GE2000.endpoint(sim)})
    assert eventually(fn -> DNC.info(cec).state == :idle end)
    %{sim: sim, cec: cec}
  end

  defp s(op, text \\ ""), do: %Command{direction: :send, operation: op, text: text}
  defp r(op, text \\ ""), do: %Command{direction: :receive, operation: op, text: text}

  defp report(cec) do
    {:ok, blocks} = DNC.request(cec, r(:status), [])
    {:ok, report} = Report.parse_status(IO.iodata_to_binary(blocks))
    report
  end

  test "a program is filed under its O word, or under the name the command gives", ctx do
    # (the simulator files a program once the link hands it over: the next request comes after)
    assert DNC.request(ctx.cec, s(:part_program), ["%\nO77\n", "M30\n%\n"]) == {:ok, []}
    assert report(ctx.cec).alarm == 0
    assert GE2000.program(ctx.sim, "000077.PRO") == "%\nO77\nM30\n%\n"
    assert DNC.request(ctx.cec, s(:part_program, "000005.GSU"), ["M99\n"]) == {:ok, []}
    assert report(ctx.cec).alarm == 0
    assert GE2000.program(ctx.sim, "000005.GSU") == "M99\n"

    assert DNC.request(ctx.cec, s(:part_program), ["N10 G00\n"]) == {:ok, []}
    assert report(ctx.cec).alarm == 2

    # the directory: name, size, CRC-16/ARC of the file's bytes
    assert {:ok, blocks} = DNC.request(ctx.cec, r(:directory), [])
    text = IO.iodata_to_binary(blocks)
    assert text =~ ~r/\A000005.GSU 000004 [0-9A-F]{4}\n000077.PRO 000012 [0-9A-F]{4}\n000100.PRO/
    {:ok, dir} = Vws.Links.DNC.Report.parse_directory(text)
    assert dir["000077.PRO"] == Vws.Links.DNC.Report.entry("000077.PRO", "%\nO77\nM30\n%\n")
    assert dir["000077.PRO"].crc == Vws.Codecs.CRC16.compute("%\nO77\nM30\n%\n")
  end

  test "a program without its closing % is refused: the old file stays (alarm 7)", ctx do
    assert DNC.request(ctx.cec, s(:part_program), ["%\nO77\nM30\n%\n"]) == {:ok, []}
    # the transmission ended early (an ENQ damaged into EOT looks like a normal end)
    assert DNC.request(ctx.cec, s(:part_program), ["%\nO77\nN5 G01\n"]) == {:ok, []}
    assert report(ctx.cec).alarm == 7
    assert GE2000.program(ctx.sim, "000077.PRO") == "%\nO77\nM30\n%\n"
    assert GE2000.state(ctx.sim).downloads == 1
  end

  # issue 24 item 3: a 1.33 MB program once went into the directory with a seven-digit size,
  # and every directory read after it failed
  test "a program over 999,999 bytes sent over DNC is not stored (alarm 8): the directory stays readable",
       ctx do
    assert DNC.request(ctx.cec, s(:part_program), ["%\nO77\nM30\n%\n"]) == {:ok, []}
    big = "%\nO77\n" <> :binary.copy("N10 G01 X1\n", 90_910) <> "%\n"
    assert byte_size(big) == 1_000_018
    blocks = Vws.Links.DNC.Frame.split_text(big, 256)
    assert DNC.request(ctx.cec, s(:part_program), blocks, 120_000) == {:ok, []}
    assert report(ctx.cec).alarm == 8
    assert GE2000.program(ctx.sim, "000077.PRO") == "%\nO77\nM30\n%\n"

    assert {:ok, dir} = DNC.request(ctx.cec, r(:directory), [])

    assert {:ok, %{"000077.PRO" => %{size: 12}}} =
             Report.parse_directory(IO.iodata_to_binary(dir))

    assert GE2000.directory(ctx.sim) == ["000077.PRO", "000100.PRO"]
  end

  test "select, cycle start, the plant told, delete refused while it runs", ctx do
    assert report(ctx.cec) == %{state: :idle, program: "000000", alarm: 0}
    GE2000.cycle_start(ctx.sim)
    assert report(ctx.cec).alarm == 4

    assert DNC.request(ctx.cec, s(:remote_control, "000100"), []) == {:ok, []}
    assert report(ctx.cec) == %{state: :idle, program: "000100", alarm: 0}
    GE2000.cycle_start(ctx.sim)
    assert_receive {:plant, :table_out_of_park}, 5_000
    assert report(ctx.cec) == %{state: :active, program: "000100", alarm: 0}

    assert DNC.request(ctx.cec, s(:delete, "000100.PRO"), []) == {:ok, []}
    assert report(ctx.cec).alarm == 3
    GE2000.end_cycle(ctx.sim)
    assert_receive {:plant, :table_in_park}, 5_000

    assert DNC.request(ctx.cec, s(:delete, "000100.PRO"), []) == {:ok, []}
    assert report(ctx.cec) == %{state: :idle, program: "000000", alarm: 0}
    assert GE2000.directory(ctx.sim) == []
  end

  test "uploads: a named file, the selected program, a missing one", ctx do
    assert DNC.request(ctx.cec, r(:part_program, "000100.PRO"), []) == {:ok, ["O100\nM30\n"]}
    assert DNC.request(ctx.cec, r(:part_program), []) == {:ok, []}
    assert report(ctx.cec).alarm == 1
    DNC.request(ctx.cec, s(:remote_control, "000100.PRO"), [])
    assert DNC.request(ctx.cec, r(:part_program), []) == {:ok, ["O100\nM30\n"]}
  end

  test "the tool-offset table: 20 lines nn ±ddd.dddd", ctx do
    {:ok, blocks} = DNC.request(ctx.cec, r(:table, "TOFFSET"), [])
    {:ok, table} = Report.parse_offsets(IO.iodata_to_binary(blocks))
    assert map_size(table) == 20
    assert table[2] == "+024.6912"
  end

  test "pace: true runs the line at 4800 Bd" do
    sim = start_supervised!({GE2000, pace: true}, id: :paced)
    assert GE2000.baud(sim) == 4800
  end

  # The line model: bytes reach the machine no faster than the baud rate carries them. Measured
  # on the monotonic clock over a whole stop-and-wait exchange, from before its first byte: the
  # line takes each reply to start no earlier than the bytes it answers were due, so the time is
  # at least every character's, one after the other — a lower bound, which a slow machine only
  # makes longer (the line's own pacing is tested in simulated time in
  # test/vws/sim/line/schedule_test.exs).
  test "pacing: bytes reach the machine no faster than the baud rate allows" do
    sim = start_supervised!({GE2000, pace: 4800}, id: :paced)
    {:ok, peer} = Vws.Test.DNCPeer.connect(GE2000.endpoint(sim))
    on_exit(fn -> if Process.alive?(peer), do: Vws.Test.DNCPeer.close(peer) end)
    text = String.duplicate("N10 G01 X1.0\n", 18) <> "%\n"
    command = Vws.Links.DNC.Frame.encode(s(:part_program, "000009.PRO")) |> IO.iodata_to_binary()

    block =
      Vws.Links.DNC.Frame.encode(%Vws.Links.DNC.Frame.Text{text: text}) |> IO.iodata_to_binary()

    started = System.monotonic_time(:microsecond)
    :ok = Vws.Test.DNCPeer.send_raw(peer, <<0x05>>)
    assert Vws.Test.DNCPeer.recv(peer, 2) == <<0x10, ?0>>
    :ok = Vws.Test.DNCPeer.send_raw(peer, command)
    assert Vws.Test.DNCPeer.recv(peer, 2) == <<0x10, ?1>>
    :ok = Vws.Test.DNCPeer.send_raw(peer, block)
    assert Vws.Test.DNCPeer.recv(peer, 2) == <<0x10, ?0>>
    elapsed = System.monotonic_time(:microsecond) - started
    # ENQ, its ACK0, the command block, its ACK1, the text block, its ACK0: 10 bits a character
    chars = 1 + 2 + byte_size(command) + 2 + byte_size(block) + 2
    assert elapsed >= div(chars * 10 * 1_000_000, 4800)
    :ok = Vws.Test.DNCPeer.send_raw(peer, <<0x04>>)
    assert eventually(fn -> GE2000.program(sim, "000009.PRO") == text end)
  end
end
