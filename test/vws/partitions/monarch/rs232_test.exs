defmodule Vws.Partitions.Monarch.RS232Test do
  # MONARCH on a plain RS-232 control (profile rs232-xonxoff), end to end: the WC (a raw WC
  # peer) → SUN_COMM → MONARCH → Vws.Links.RS232 → the simulated control (Vws.Sim.RS232Control).
  use ExUnit.Case, async: true

  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.Links.DNC.Program
  alias Vws.Sim.RS232Control
  alias Vws.Test.WCPeer
  import Vws.Test.Eventually

  @moduletag :tmp_dir

  setup context do
    sim_opts = Keyword.merge([buffer: 512, rate: 1_500], Map.get(context, :sim, []))
    sim = start_supervised!({RS232Control, sim_opts})

    port = [
      endpoint: RS232Control.endpoint(sim),
      profile: "rs232-xonxoff",
      baud: 19_200,
      backoff_min: 10,
      read_back_timeout: 5_000,
      upload_timeout: 10_000
    ]

    %{ws: ws, wc: wc} =
      Vws.Test.Workstation.start(devices: [ge2000: port], library: context.tmp_dir)

    link = Workstation.whereis(ws, :ge2000)
    assert eventually(fn -> Vws.Links.RS232.info(link).state == :idle end)
    assert eventually(fn -> RS232Control.info(sim).connected end)
    {:ok, peer} = WCPeer.connect(wc)
    %{ws: ws, peer: peer, sim: sim, link: link}
  end

  import Vws.Test.Serial, only: [send_monarch: 3, finished: 1, monarch: 3]

  defp program(bytes, number \\ "O4711"), do: Vws.Test.Serial.program_lines(bytes, number)

  # (busy at the start: it says XOFF whatever the pace of a loaded host's sender)
  @tag sim: [punch_after_load: true, busy_until_xoff: true]
  test "DOWNLOAD_GE is DONE once the control's read-back is the program sent", ctx do
    lines = program(3_000)
    :ok = Mailbox.put_nc_file(ctx.ws, lines)
    assert monarch(ctx.peer, 1, "DOWNLOAD_GE") == "0001DONE"
    info = RS232Control.info(ctx.sim)
    assert info.programs["004711.PRO"] == Program.to_text(lines)
    assert info.xoffs > 0 and info.dropped == 0
  end

  test "DOWNLOAD_GE without a read-back is not DONE: it says why", ctx do
    :ok = Mailbox.put_nc_file(ctx.ws, program(300))

    assert monarch(ctx.peer, 1, "DOWNLOAD_GE") ==
             "0001ERROR PROGRAM NOT VERIFIED NO READ BACK WITHIN 5 S"
  end

  @tag sim: [punch_after_load: true]
  test "a bit flipped on the way to the control: DOWNLOAD_GE ends ERROR", ctx do
    :ok = Mailbox.put_nc_file(ctx.ws, program(600))
    :ok = RS232Control.set_fault(ctx.sim, {:flip, 40, 2})

    assert monarch(ctx.peer, 1, "DOWNLOAD_GE") ==
             "0001ERROR PROGRAM VERIFY FAILED READ BACK DIFFERS"
  end

  # (busy at the start: it says XOFF whatever the pace of a loaded host's sender)
  @tag sim: [busy_until_xoff: true]
  test "DRIP_FEED: every byte reaches the control under XON/XOFF, its progress published", ctx do
    lines = program(4_000)
    :ok = Mailbox.put_nc_file(ctx.ws, lines)
    :ok = Vws.CEC.Events.subscribe(ctx.ws, :dnc_progress)
    assert monarch(ctx.peer, 1, "DRIP_FEED") == "0001DONE"

    progress = collect_progress([])
    total = byte_size(Program.to_text(lines))
    assert length(progress) > 10
    assert %{ended: :ok, operation: :download_execute, program: "004711.PRO"} = hd(progress)
    assert hd(progress).total_program_bytes == total and hd(progress).program_bytes == total
    assert hd(progress).pauses > 0
    # the machine runs the program as it arrives: MONARCH says so (and, no report to read, keeps
    # saying so: a plain RS-232 control cannot tell when it is done)
    assert elem(Mailbox.get_device(ctx.ws, 8), 0) == "ACTIVE"

    # (30 s: the control runs what it received at its own pace, which a loaded host slows)
    assert eventually(fn -> RS232Control.info(ctx.sim).last == Program.to_text(lines) end, 30_000)
    assert RS232Control.info(ctx.sim).dropped == 0
    # a plain RS-232 control cannot say when it is idle: the table stays the machine's
    assert monarch(ctx.peer, 2, "RELEASE_TABLE") ==
             "0002ERROR NO STATUS REPORT FROM AN RS-232 CONTROL"
  end

  # newest first
  defp collect_progress(acc) do
    receive do
      {:vws_event, _, :dnc_progress, payload} -> collect_progress([payload | acc])
    after
      500 -> acc
    end
  end

  test "UPLOAD_GE takes the program the operator punches into NC_UP", ctx do
    text = Program.to_text(program(800))
    :ok = RS232Control.set_fault(ctx.sim, nil)
    send_monarch(ctx.peer, 1, "UPLOAD_GE(004711.PRO)")
    assert eventually(fn -> Vws.Links.RS232.info(ctx.link).state == :awaiting end)
    # the operator's PUNCH of a program the control holds
    :sys.replace_state(ctx.sim, &%{&1 | programs: %{"004711.PRO" => text}})
    :ok = RS232Control.punch(ctx.sim, "004711.PRO")
    assert finished(ctx.peer) == "0001DONE"
    assert Mailbox.nc_up(ctx.ws) == Program.from_text(text)
  end

  test "what the control cannot do ends ERROR in words", ctx do
    for {n, command, words} <- [
          {1, "STATUS", "NO STATUS REPORT FROM AN RS-232 CONTROL"},
          {2, "PROGRAM_SELECT(004711)", "NO REMOTE PROGRAM SELECT ON AN RS-232 CONTROL"},
          {3, "PROGRAM_DELETE(004711.PRO)", "NO REMOTE DELETE ON AN RS-232 CONTROL"},
          {4, "TABLE(1/2)", "NO TOOL-OFFSET TABLE FROM AN RS-232 CONTROL"},
          {5, "COMPARE_GE", "NO DIRECTORY ON AN RS-232 CONTROL"}
        ] do
      number = String.pad_leading("#{n}", 4, "0")
      assert monarch(ctx.peer, n, command) == "#{number}ERROR #{words}"
    end
  end

  test "COMPARE_GE(nnnnnn.PRO) without a directory: the program the operator punches, compared",
       ctx do
    text = Program.to_text(program(600))
    {:ok, _} = Vws.CEC.Library.store(ctx.ws, "004711.PRO", text, source: "test")

    for {n, punched, status} <- [
          {1, text, "0001DONE"},
          {2, String.replace(text, "X37.1", "X37.2"),
           "0002ERROR PROGRAM DIFFERS 004711.PRO FROM V1 LINES -1 +1 AT LINE 3"}
        ] do
      :sys.replace_state(ctx.sim, &%{&1 | programs: %{"004711.PRO" => punched}})
      send_monarch(ctx.peer, n, "COMPARE_GE(004711.PRO)")
      assert eventually(fn -> Vws.Links.RS232.info(ctx.link).state == :awaiting end)
      :ok = RS232Control.punch(ctx.sim, "004711.PRO")
      assert finished(ctx.peer) == status
    end
  end

  test "a program punched at the control unasked goes to the library, not released", ctx do
    text = Program.to_text(program(300, "O77"))
    :sys.replace_state(ctx.sim, &%{&1 | programs: %{"000077.PRO" => text}})
    :ok = RS232Control.punch(ctx.sim, "000077.PRO")

    assert eventually(fn ->
             match?({:ok, [_]}, Vws.CEC.Library.versions(ctx.ws, "000077.PRO"))
           end)

    {:ok, [v]} = Vws.CEC.Library.versions(ctx.ws, "000077.PRO")
    assert v.source == "from the machine"
  end
end
