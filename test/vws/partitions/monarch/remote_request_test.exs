defmodule Vws.Partitions.Monarch.RemoteRequestTest do
  # The operator at the GE-2000 asks for a program from the machine's panel (issue 27 item 1),
  # end to end over the DNC wire: simulated GE-2000 (RCS + nnnnnn.PRO[/v]) → DNC link → MONARCH's
  # monitor → the program library, and the answer back the same way.
  use ExUnit.Case, async: true

  alias Vws.CEC.{Interlock, Library, Workstation}
  alias Vws.Links.DNC
  alias Vws.Partitions.Monarch
  alias Vws.Sim.GE2000
  import Vws.Test.Eventually

  @link_opts [reply_timeout: 300, wack_delay: 50, backoff_min: 10, backoff_max: 50]
  @v1 "%\nO55 (FIRST)\nN10 G01 X1 F100\nN20 M30\n%\n"
  @v2 "%\nO55 (SECOND)\nN10 G01 X2 F100\nN20 M30\n%\n"

  setup do
    dir = Path.join(System.tmp_dir!(), "vws-remote-request-#{System.unique_integer([:positive])}")
    on_exit(fn -> File.rm_rf!(dir) end)
    sim = start_supervised!({GE2000, link: @link_opts, cycle_time: 60_000})

    %{ws: ws} =
      Vws.Test.Workstation.start(
        devices: [ge2000: [endpoint: GE2000.endpoint(sim), status_interval: nil] ++ @link_opts],
        library: dir
      )

    link = Workstation.whereis(ws, :ge2000)
    assert eventually(fn -> DNC.info(link).state == :idle end)

    me = self()
    id = "remote-request-#{System.unique_integer([:positive])}"

    :ok =
      Vws.Telemetry.attach(
        id,
        [:vws, :monarch, :remote_request],
        fn _, m, md, _ -> if md.workstation == ws, do: send(me, {:remote_request, m, md}) end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
    %{ws: ws, sim: sim}
  end

  defp file(n) when is_integer(n), do: String.pad_leading("#{n}", 6, "0") <> ".PRO"
  defp file(name), do: name

  test "the latest released version is sent and filed; a named released version too; logged",
       %{ws: ws, sim: sim} do
    {:ok, _} = Library.store(ws, "55", @v1, source: "iex")
    {:ok, _} = Library.store(ws, "55", @v2, source: "iex")
    :ok = Vws.CEC.Events.subscribe(ws, :dnc_progress)

    assert GE2000.Panel.request_program(sim, 55) == :ok
    assert GE2000.program(sim, "000055.PRO") == @v2
    assert GE2000.state(sim).alarm == 0
    bytes = byte_size(@v2)

    # checked as after any DOWNLOAD_GE: the report and the directory say the machine holds it
    assert_receive {:remote_request, %{bytes: ^bytes},
                    %{program: "000055.PRO", version: 2, result: :sent, verified: :ok}},
                   5_000

    # the answer is a transfer of the link like any other: its progress names the program
    assert_receive {:vws_event, ^ws, :dnc_progress,
                    %{program: "000055.PRO", direction: :out, ended: :ok}},
                   5_000

    assert GE2000.Panel.request_program(sim, "000055", 1) == :ok
    assert GE2000.program(sim, "000055.PRO") == @v1
    assert_receive {:remote_request, _, %{version: 1, result: :sent, verified: :ok}}, 5_000
    # (the version the operator named is not part of the file's name)
    assert_receive {:vws_event, ^ws, :dnc_progress, %{program: "000055.PRO", ended: :ok}}, 5_000

    # both in the transfer history, through its one home, as the machine panel's
    {:ok, %{records: [second, first], damaged: []}} = Library.history(ws)

    assert {first.program, first.version, first.result, first.requester, first.direction} ==
             {"000055.PRO", 2, "DONE", "machine panel", "to machine"}

    assert {first.command, first.bytes} == {"REQUESTED FROM THE MACHINE 000055.PRO", bytes}
    assert {second.version, second.command} == {1, "REQUESTED FROM THE MACHINE 000055.PRO/1"}

    # what the machine holds is what the library says it holds
    {:ok, compare} = Monarch.compare(ws)
    assert [%{name: "000055.PRO", on_machine: {:same, 1}}] = compare.programs
  end

  test "a machine that files other bytes than it was sent: the request is logged NOT verified",
       %{ws: ws, sim: sim} do
    {:ok, _} = Library.store(ws, "55", @v1, source: "iex")
    :ok = GE2000.set_fault(sim, {:file_as, &String.replace(&1, "X1", "X9")})
    assert GE2000.Panel.request_program(sim, 55) == :ok

    assert_receive {:remote_request, _,
                    %{result: :sent, verified: {:error, "PROGRAM VERIFY FAILED 000055.PRO"}}},
                   5_000

    {:ok, %{records: [r]}} = Library.history(ws)
    assert {r.result, r.version} == {"ERROR PROGRAM VERIFY FAILED 000055.PRO", 1}
  end

  test "refused in words the operator sees: nothing filed, alarm 9, the message on the screen",
       %{ws: ws, sim: sim} do
    {:ok, _} = Library.store(ws, "55", @v1, source: "iex")
    # version 2 came from the machine: not released
    :ok = Monarch.store_from_machine(ws, "000055.PRO", Vws.Links.DNC.Program.from_text(@v2))
    :ok = Monarch.store_from_machine(ws, "000056.PRO", Vws.Links.DNC.Program.from_text(@v2))
    # released, but more than the machine stores (the library keeps it for drip feeds)
    big = "%\nO58\n" <> String.duplicate("N1000 G01 X100.5\n", 60_000) <> "M30\n%\n"
    {:ok, _} = Library.store(ws, "58", big, source: "iex")

    cases = [
      {{58, nil}, "PROGRAM TOO LARGE #{byte_size(big)} BYTES (LIMIT 999999)"},
      {{"000055.PRO", 2}, "000055.PRO VERSION 2 NOT RELEASED"},
      {{"000056.PRO", nil}, "000056.PRO HAS NO RELEASED VERSION"},
      {{57, nil}, "000057.PRO NOT IN LIBRARY"},
      {{55, 9}, "000055.PRO VERSION 9 NOT IN LIBRARY"}
    ]

    for {{number, version}, words} <- cases do
      # a comment ends at its first ")": the words' own parentheses are not in the message
      shown = "REQUEST REFUSED " <> String.replace(words, ["(", ")"], "")

      assert GE2000.Panel.request_program(sim, number, version) ==
               {:error, {:refused, shown}}

      assert GE2000.state(sim).alarm == 9
      assert hd(GE2000.state(sim).messages) == shown
      # (told once its record is in the history: the check after an answer runs apart)
      assert_receive {:remote_request, _, %{result: :refused, reason: ^words}}, 5_000
    end

    assert GE2000.directory(sim) == []
    assert GE2000.state(sim).downloads == 0

    # each refusal in the history: nothing sent, the words the operator saw
    {:ok, %{records: records}} = Library.history(ws)

    assert Enum.map(Enum.reverse(records), &{&1.program, &1.bytes, &1.result}) ==
             for({{n, _v}, words} <- cases, do: {file(n), 0, "ERROR REQUEST REFUSED " <> words})

    assert GE2000.Panel.request_program(sim, "12.PRO") == {:error, :bad_name}
  end

  test "the interlock is DOWNLOAD_GE's, decided by the one table: a program goes to the machine " <>
         "while the robot holds the table (nothing moves); the table stays the robot's",
       %{ws: ws, sim: sim} do
    assert Vws.CEC.Interlock.Rules.rule(:monarch, {:download_ge, "000055.PRO", :latest}) ==
             {:ok, :none}

    {:ok, _} = Library.store(ws, "55", @v1, source: "iex")
    :ok = Interlock.acquire(ws, :table, :robot, 0)
    assert GE2000.Panel.request_program(sim, 55) == :ok
    assert GE2000.program(sim, "000055.PRO") == @v1
    assert Interlock.holds?(ws, :table, :robot)
    assert_receive {:remote_request, _, %{result: :sent, verified: :ok}}, 10_000
  end

  # The machine asks while the CEC reads its status: an R command of the CEC's that reaches the
  # machine before the machine's own could go out holds the half-duplex line until answered. The
  # simulated control used to keep it waiting for its own request's answer — which could not come
  # before — and both sat until the link's answer_timeout (alarm 7 on the machine: the CEC's next
  # bid read as the program's text).
  test "requests one after another while the CEC reads the machine's status: every one answered",
       %{ws: ws, sim: sim} do
    {:ok, _} = Library.store(ws, "55", @v1, source: "iex")
    link = Workstation.whereis(ws, :ge2000)

    reader = Task.async(fn -> for _ <- 1..30, do: Monarch.refresh_status(ws, link) end)
    results = for _ <- 1..20, do: GE2000.Panel.request_program(sim, 55)
    reads = Task.await(reader, 60_000)

    assert Enum.frequencies(results) == %{:ok => 20}
    # and each one checked on the machine after it (the check runs apart from the answer)
    for _ <- 1..20, do: assert_receive({:remote_request, _, %{verified: :ok}}, 10_000)
    assert Enum.count(reads, &match?({:ok, _}, &1)) > 0
    assert GE2000.state(sim).alarm == 0
  end

  # The check after an answer reads the machine's report and directory over the same link: the
  # owner that answers must not wait for it, or an R command that comes meanwhile (the machine's
  # next request) finds it held up, unanswered until the link's answer_timeout.
  test "the answer goes out and the owner is free at once; the check after it runs apart",
       %{ws: ws} do
    {:ok, _} = Library.store(ws, "55", @v1, source: "iex")
    test = self()

    # a link that takes the answer and holds every request of the check unanswered
    link =
      spawn(fn ->
        hold = fn hold ->
          receive do
            {:"$gen_call", from, :info} ->
              :gen.reply(from, %{max_text: 256, counters: %{}})

            {:"$gen_call", from, {:answer, _ref, blocks}} ->
              :gen.reply(from, :ok)
              send(test, {:answered, blocks})

            _held ->
              :ok
          end

          hold.(hold)
        end

        hold.(hold)
      end)

    command = %Vws.Links.DNC.Frame.Command{
      direction: :receive,
      check: :crc,
      operation: :part_program,
      text: "000055.PRO"
    }

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        answering =
          Task.async(fn -> Monarch.RemoteRequest.answer(ws, link, make_ref(), command) end)

        assert Task.yield(answering, 2_000) == {:ok, {:sent, "000055.PRO", 1}}
        assert_receive {:answered, blocks}
        assert IO.iodata_to_binary(blocks) == @v1

        # the link goes away under the check: the check ends NOT verified, told and logged
        refute_received {:remote_request, _, _}
        Process.exit(link, :kill)
        assert_receive {:remote_request, _, %{result: :sent, verified: {:error, _}}}, 10_000
      end)

    assert log =~
             "MONARCH: the machine asked for 000055.PRO: sent 000055.PRO version 1, NOT verified"
  end

  test "the CEC answers with the wire's own words: RCS + nnnnnn.PRO/v, then the program's blocks" do
    # the GE's command block as it goes on the line, and the refusal as the machine reads it
    command = %Vws.Links.DNC.Frame.Command{
      direction: :receive,
      check: :crc,
      operation: :part_program,
      text: "000055.PRO/2"
    }

    assert <<0x01, "RCS", 0x02, "000055.PRO/2", 0x03, _crc::binary-2>> =
             IO.iodata_to_binary(Vws.Links.DNC.Frame.encode(command))

    assert Monarch.RemoteRequest.refusal("000055.PRO NOT IN LIBRARY") ==
             "(MSG,REQUEST REFUSED 000055.PRO NOT IN LIBRARY)\n"

    refute Vws.Links.DNC.Program.complete?(Monarch.RemoteRequest.refusal("X"))
  end
end
