defmodule Vws.Links.RS232.LinkTest do
  # The plain RS-232 port against the simulated control (Vws.Sim.RS232Control), over TCP.
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.{RS232, Transport}
  alias Vws.Links.DNC.Frame.Command
  alias Vws.Sim.RS232Control

  import Vws.Test.Eventually

  @send %Command{direction: :send, operation: :part_program}
  @drip %Command{direction: :send, operation: :download_execute}

  defp program(bytes, number \\ "O4711"), do: Vws.Test.Serial.program_text(bytes, number)

  defp start(ctx, sim_opts, link_opts \\ []) do
    sim = start_sim(Keyword.merge([buffer: 1024, rate: 4_000], sim_opts))

    {:ok, link} =
      RS232.start_link(
        Keyword.merge(
          [endpoint: RS232Control.endpoint(sim), owner: self(), baud: 19_200, backoff_min: 10],
          link_opts
        )
      )

    assert_receive {:dnc, ^link, :connected}, 5_000
    # (the control takes the connection a moment after the link has it)
    assert eventually(fn -> RS232Control.info(sim).connected end)
    Map.merge(ctx, %{sim: sim, link: link})
  end

  defp start_sim(opts),
    do: start_supervised!(Supervisor.child_spec({RS232Control, opts}, id: make_ref()))

  test "a download goes at the line's pace under XON/XOFF and is DONE on an identical read-back",
       ctx do
    # (busy at the start: it says XOFF whatever the pace of a loaded host's sender)
    %{sim: sim, link: link} = start(ctx, punch_after_load: true, rate: 800, busy_until_xoff: true)
    text = program(4_000)
    assert RS232.request(link, @send, [text], 30_000) == {:ok, []}
    info = RS232Control.info(sim)
    # it said XOFF, and lost nothing
    assert info.xoffs > 0 and info.xons > 0
    assert info.dropped == 0
    assert info.max_fill <= 1024
    assert info.programs["004711.PRO"] == text
    assert RS232.info(link).xoffs == info.xoffs
  end

  test "a sender that ignores XOFF is caught: the control drops bytes and its program differs" do
    sim = start_sim(buffer: 256, rate: 1_000)
    {:ok, conn} = Transport.connect(RS232Control.endpoint(sim))
    text = program(3_000)
    {:ok, f} = Vws.Links.RS232.Framing.new([])
    # all at once, whatever the control says
    :ok = Transport.send(conn, Vws.Links.RS232.Framing.encode(text, f))
    assert eventually(fn -> RS232Control.info(sim).dropped > 0 end)
    info = RS232Control.info(sim)
    assert :overrun in info.alarms
    assert info.xoffs > 0
    # what it kept (if it could read a program at all) is not what was sent
    refute Map.get(info.programs, "004711.PRO") == text
    Transport.close(conn)
  end

  test "the same sender through the link: the read-back catches a control that lost bytes", ctx do
    # a control whose XOFF comes too late for its buffer (high water above its size)
    %{link: link} =
      start(ctx, [punch_after_load: true, buffer: 64, high: 1_000, rate: 500],
        read_back_timeout: 2_000
      )

    # what the control kept differs, or is not a program at all (a % or an end of line lost)
    assert RS232.request(link, @send, [program(2_000)], 30_000) in [
             {:error, "PROGRAM VERIFY FAILED READ BACK DIFFERS"},
             {:error, "PROGRAM NOT VERIFIED NO READ BACK WITHIN 2 S"}
           ]
  end

  test "an XOFF that never ends is a bounded wait ending in words", ctx do
    %{sim: sim, link: link} = start(ctx, [rate: 200], xoff_timeout: 300)
    :ok = RS232Control.set_fault(sim, :never_xon)

    assert RS232.request(link, @drip, [program(3_000)], 30_000) ==
             {:error, "XOFF FROM THE CONTROL FOR OVER 0.3 S"}

    # the link is free again
    assert RS232.info(link).state == :idle
  end

  test "waiting for the control's DC1: it comes, or the wait ends in words", ctx do
    %{link: link} = start(ctx, [ready_dc1: true, punch_after_load: true], wait_dc1: true)
    assert RS232.request(link, @send, [program(500)], 30_000) == {:ok, []}
    # and once more: the control said DC1 again after the program
    assert RS232.request(link, @send, [program(500, "O4712")], 30_000) == {:ok, []}

    %{link: link} = start(ctx, [], wait_dc1: true, dc1_timeout: 200)

    assert RS232.request(link, @send, [program(500)], 30_000) ==
             {:error, "NO DC1 FROM THE CONTROL WITHIN 0.2 S"}
  end

  test "no read-back: the download is not DONE; verify: :none is the shop's choice", ctx do
    %{link: link} = start(ctx, [], read_back_timeout: 300)

    assert RS232.request(link, @send, [program(500)], 30_000) ==
             {:error, "PROGRAM NOT VERIFIED NO READ BACK WITHIN 0.3 S"}

    %{link: link} = start(ctx, [], verify: :none)
    assert RS232.request(link, @send, [program(500)], 30_000) == {:ok, []}
  end

  test "drip feed: every byte sent under flow control, nothing read back", ctx do
    %{sim: sim, link: link} = start(ctx, rate: 1_000)
    text = program(3_000)
    assert RS232.request(link, @drip, [text], 30_000) == {:ok, []}
    assert eventually(fn -> RS232Control.info(sim).last == text end)
    assert RS232Control.info(sim).dropped == 0
  end

  test "upload: the program the operator punches, by name; another one is refused", ctx do
    text = program(800)
    other = program(300, "O99")

    %{sim: sim, link: link} = start(ctx, programs: %{"004711.PRO" => text, "000099.PRO" => other})

    upload = %Command{direction: :receive, operation: :part_program, text: "004711.PRO"}
    task = Task.async(fn -> RS232.request(link, upload, [], 30_000) end)
    assert eventually(fn -> RS232.info(link).state == :awaiting end)
    :ok = RS232Control.punch(sim, "004711.PRO")
    assert Task.await(task) == {:ok, [text]}

    task = Task.async(fn -> RS232.request(link, upload, [], 30_000) end)
    assert eventually(fn -> RS232.info(link).state == :awaiting end)
    :ok = RS232Control.punch(sim, "000099.PRO")
    assert Task.await(task) == {:error, "CONTROL SENT 000099.PRO NOT 004711.PRO"}
  end

  test "a program punched unasked goes to the owner, named by its number", ctx do
    text = program(300, "O77")
    %{sim: sim, link: link} = start(ctx, programs: %{"000077.PRO" => text})
    :ok = RS232Control.punch(sim, "000077.PRO")
    assert_receive {:dnc, ^link, {:received, %Command{text: "000077.PRO"}, [^text]}}, 5_000
  end

  test "what a plain RS-232 control cannot do is refused in words", ctx do
    %{link: link} = start(ctx, [])

    for {op, dir, words} <- [
          {:status, :receive, "NO STATUS REPORT FROM AN RS-232 CONTROL"},
          {:directory, :receive, "NO DIRECTORY ON AN RS-232 CONTROL"},
          {:table, :receive, "NO TOOL-OFFSET TABLE FROM AN RS-232 CONTROL"},
          {:remote_control, :send, "NO REMOTE PROGRAM SELECT ON AN RS-232 CONTROL"},
          {:delete, :send, "NO REMOTE DELETE ON AN RS-232 CONTROL"}
        ] do
      assert RS232.request(link, %Command{direction: dir, operation: op}, [], 5_000) ==
               {:error, words}
    end

    assert RS232.request(link, @send, ["%\nO1\n"], 5_000) == {:error, "PROGRAM HAS NO CLOSING %"}
  end

  test "bit flips on the line: a download is never DONE with other bytes", ctx do
    # (a flip that breaks the framing leaves the control without a program: no read-back; one
    # that makes a DC3 is an XOFF when the program is punched back, which no XON ends)
    %{sim: sim, link: link} =
      start(ctx, [punch_after_load: true], read_back_timeout: 500, xoff_timeout: 500)

    text = program(400)

    property =
      :proper.forall(
        {:proper_types.integer(0, byte_size(text) - 1), :proper_types.integer(0, 7)},
        fn {n, bit} ->
          :ok = RS232Control.set_fault(sim, {:flip, n, bit})
          result = RS232.request(link, @send, [text], 30_000)
          stored = RS232Control.info(sim).last
          # DONE only if the control holds exactly the bytes sent (never, a bit having flipped)
          match?({:error, _}, result) and (result != {:ok, []} or stored == text)
        end
      )

    assert_property(property, 30)
  end

  test "an endpoint whose driver would take the XON/XOFF itself is refused, in words" do
    assert_raise ArgumentError, ~r/has flow=xonxoff, .* give flow=none/, fn ->
      RS232.start_link(endpoint: "rfc2217://127.0.0.1:2001?flow=xonxoff")
    end
  end

  test "unknown framing options are refused at start, in words" do
    assert_raise ArgumentError,
                 "RS-232 link: framing: eol is :lf, :cr or :crlf (got :lfcr)",
                 fn ->
                   RS232.start_link(framing: [eol: :lfcr])
                 end
  end
end
