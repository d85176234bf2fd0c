defmodule Vws.Reliability.JournalServeTest do
  # Issues 24 B and 30 as a user meets them: `mix vws.serve` in an OS process. The rule-2 string
  # that bricked every later start, then SIGTERM and kill -9; a journal damaged on disk; a journal
  # directory that cannot be made.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 300_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp serve(journal) do
    wc = Acceptance.free_port()

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "0", "--journal", journal],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    %{proc: proc, wc: wc}
  end

  defp status(wc, seq, name) do
    reply = Acceptance.wc_request(wc, "*#{pad4(seq)}*S#{pad4(seq)}#{name}*")
    [_, text] = Regex.run(~r/^\d\dS#{pad4(seq)}(.*)\d{3}$/, reply)
    text
  end

  defp pad4(n), do: String.pad_leading(Integer.to_string(n), 4, "0")

  defp kill_9(proc) do
    Acceptance.signal(proc, "KILL")
    assert Acceptance.await_exit(proc, 30_000) in [137, 9]
  end

  test "*0001*S0001VISE*G0001OPEN*, then SIGTERM, kill -9 and a damaged journal: it starts again every time and answers",
       %{tmp_dir: dir} do
    journal = Path.join(dir, "journal")
    %{proc: proc, wc: wc} = serve(journal)

    assert Acceptance.wc_request(wc, "*0001*S0001VISE*G0001OPEN*") =~ ~r/^05A0001\d{3}$/
    rule2 = "0001ERROR RULE 2 STATUS COMMAND NOT ALONE"
    assert status(wc, 2, "GRIPPER_CMD") == rule2

    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 30_000) == 0, Acceptance.output(proc)

    # SIGTERM: it starts again and answers as before
    %{proc: proc, wc: wc} = serve(journal)
    assert status(wc, 3, "GRIPPER_CMD") == rule2
    assert status(wc, 4, "VISE_CMD") == "0000NONE"
    assert Acceptance.wc_request(wc, "*0005*F0001NONSENSE*") =~ ~r/^05A0005\d{3}$/

    fixture =
      Acceptance.await_command(
        wc,
        "FIXTURE_CMD",
        6,
        1,
        System.monotonic_time(:millisecond) + 30_000
      )

    [_, fixture] = Regex.run(~r/^\d\dS\d{4}(.*)\d{3}$/, fixture)
    assert fixture =~ ~r/^0001ERROR /
    kill_9(proc)

    # kill -9: the same
    %{proc: proc, wc: wc} = serve(journal)
    assert status(wc, 100, "GRIPPER_CMD") == rule2
    assert status(wc, 101, "FIXTURE_CMD") == fixture
    kill_9(proc)

    # 8 bytes flipped a third of the way into the journal: the statuses it held say they are
    # unknown, never an older one; the damage is in the log and the file kept aside
    path = Path.join(journal, "journal.log")
    bin = File.read!(path)
    at = div(byte_size(bin), 3)
    <<a::binary-size(at), b::binary-size(8), rest::binary>> = bin
    File.write!(path, [a, :crypto.exor(b, :binary.copy(<<0xFF>>, 8)), rest])

    %{proc: proc, wc: wc} = serve(journal)
    assert Acceptance.output(proc) =~ ~r/damaged at byte \d+ of .*journal\.log/

    for {name, seq, truth} <- [{"GRIPPER_CMD", 200, rule2}, {"FIXTURE_CMD", 201, fixture}] do
      assert status(wc, seq, name) in [truth, "0000NO DATA (JOURNAL DAMAGED)"]
    end

    assert status(wc, 202, "VACUUM_CMD") in ["0000NONE", "0000NO DATA (JOURNAL DAMAGED)"]
    assert [_] = Path.wildcard(Path.join(journal, "journal.damaged-*"))

    # and it takes work
    assert Acceptance.wc_request(wc, "*0203*G0002OPEN*") =~ ~r/^05A0203\d{3}$/
    kill_9(proc)

    # an empty journal: everything unknown, in words
    File.write!(path, "")
    %{proc: proc, wc: wc} = serve(journal)
    assert status(wc, 300, "GRIPPER_CMD") == "0000NO DATA (JOURNAL DAMAGED)"
    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 30_000) == 0
  end

  test "a journal directory that cannot be made: mix vws.serve exits non-zero with the reason in one line",
       %{tmp_dir: dir} do
    file = Path.join(dir, "a-file")
    File.write!(file, "")

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{Acceptance.free_port()}", "--http-port", "0"] ++
          ["--journal", Path.join(file, "journal")],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    status = Acceptance.await_exit(proc, 120_000)
    output = Acceptance.output(proc)
    assert status != 0, output

    assert output =~
             ~r/workstation VWS did not start: journal directory \S+ cannot be made: not a directory\n/
  end

  @root? match?({"0\n", 0}, System.cmd("id", ["-u"]))

  @tag skip: if(@root?, do: false, else: "needs root to mount a tmpfs")
  test "a full disk under mix vws.serve: refused or ERROR JOURNAL WRITE FAILED, never DONE; space back, work, kill -9, all there",
       %{tmp_dir: dir} do
    mnt = Path.join(dir, "small")
    File.mkdir_p!(mnt)
    {_, 0} = System.cmd("mount", ["-t", "tmpfs", "-o", "size=256k", "tmpfs", mnt])
    on_exit(fn -> System.cmd("umount", ["-l", mnt]) end)
    journal = Path.join(mnt, "journal")
    %{proc: proc, wc: wc} = serve(journal)
    deadline = fn -> System.monotonic_time(:millisecond) + 30_000 end

    assert Acceptance.wc_request(wc, "*0001*F0001NONSENSE*") =~ ~r/^05A0001\d{3}$/
    assert Acceptance.await_command(wc, "FIXTURE_CMD", 2, 1, deadline.()) =~ ~r/0001ERROR /

    # the disk full
    {:ok, fd} = :file.open(Path.join(mnt, "filler"), [:write, :raw, :binary])
    chunk = :binary.copy(<<0>>, 4096)
    Stream.repeatedly(fn -> :file.write(fd, chunk) end) |> Enum.find(&(&1 != :ok))
    :file.close(fd)

    # strings until the journal cannot take one: refused (E), or the command ends ERROR
    # JOURNAL WRITE FAILED; never DONE
    last =
      Enum.find_value(10..200, fn n ->
        case Acceptance.wc_request(wc, "*#{pad4(n)}*F#{pad4(n)}NONSENSE*") do
          "E" ->
            n

          ack ->
            assert ack =~ ~r/^05A#{pad4(n)}\d{3}$/
            status = Acceptance.await_command(wc, "FIXTURE_CMD", 1000 + n, n, deadline.())
            refute status =~ "DONE"
            if status =~ "ERROR JOURNAL WRITE FAILED", do: n
        end
      end)

    assert is_integer(last)
    # no work while it is full
    assert Acceptance.wc_request(wc, "*0500*G0500OPEN*") == "E"
    assert status(wc, 501, "GRIPPER_CMD") == "0000NONE"
    # (the node's log line reaches its output a little after the refusal, on a loaded machine)
    Acceptance.await(proc, ~r/no space left on device/, 15_000)

    # space again: within a few seconds strings are taken
    File.rm!(Path.join(mnt, "filler"))

    assert Enum.any?(1..60, fn i ->
             Acceptance.wc_request(wc, "*#{pad4(600 + i)}*F0700NONSENSE*") =~ ~r/^05A/ or
               (Process.sleep(500) && false)
           end)

    fixture = Acceptance.await_command(wc, "FIXTURE_CMD", 800, 700, deadline.())
    [_, fixture] = Regex.run(~r/^\d\dS\d{4}(.*)\d{3}$/, fixture)
    assert fixture =~ ~r/^0700ERROR /
    assert Acceptance.output(proc) =~ "healthy again"
    kill_9(proc)

    # everything acknowledged after the full disk is there
    %{proc: proc, wc: wc} = serve(journal)
    assert status(wc, 900, "FIXTURE_CMD") == fixture
    assert status(wc, 901, "GRIPPER_CMD") == "0000NONE"
    refute Acceptance.output(proc) =~ "damaged at byte"
    kill_9(proc)
  end
end
