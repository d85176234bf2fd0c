defmodule Vws.Acceptance.DripFeedTaskTest do
  # `mix vws.drip_feed` as docs/dnc-drip-feed.md runs it: a real OS process, a program file,
  # the simulated GE-2000 on a paced line; the exit status says whether the program got there.
  use ExUnit.Case, async: true

  alias Vws.CEC.Library
  alias Vws.Codecs.NCModal
  alias Vws.Links.DNC.Program
  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 180_000
  @moduletag :tmp_dir

  setup_all do
    Acceptance.prebuild("dev")
  end

  test "mix vws.drip_feed: a program larger than the machine's memory, run while it arrives",
       %{tmp_dir: dir} do
    lines = ["%", "O77"] ++ for(i <- 1..400, do: "N#{i} G01 X#{i}.5 F300") ++ ["M30", "%"]
    file = Path.join(dir, "part.nc")
    File.write!(file, Enum.join(lines, "\n") <> "\n")
    size = File.stat!(file).size
    args = ["--baud", "96000", "--memory", "2048", "--feed-rate", "600"]
    proc = Acceptance.start(["mix", "vws.drip_feed", file | args], env: [{"MIX_ENV", "dev"}])
    on_exit(fn -> Acceptance.stop(proc) end)

    assert Acceptance.await_exit(proc, 120_000) == 0, Acceptance.output(proc)
    output = Acceptance.output(proc)
    assert output =~ "000077.PRO: the whole program reached the machine"
    crc = Integer.to_string(Vws.Codecs.CRC16.compute(File.read!(file)), 16)

    assert output =~
             ~r/received #{size} bytes, ran #{size}, buffer \d+\/2048 at most, 0 underruns, CRC #{crc}, state done/

    # a file that is no whole program is refused before anything is sent
    File.write!(file, "O77\nN1 G01 X1\n")
    proc = Acceptance.start(["mix", "vws.drip_feed", file], env: [{"MIX_ENV", "dev"}])
    assert Acceptance.await_exit(proc, 60_000) != 0
    assert Acceptance.output(proc) =~ "no closing % line"
  end

  test "mix vws.drip_feed --program: a released library version, restarted at a line with its preamble shown first",
       %{tmp_dir: dir} do
    library = Path.join(dir, "library")
    lib = {:dir, library}
    body = for i <- 1..300, do: "N#{i} G01 X#{i}.5 F300"

    lines =
      ["%", "O77", "G21 G17 G90 G54", "T3 M6", "S1500 M3", "M8"] ++
        body ++ ["G81 X10 Y10 Z-5 R1 F80", "X20", "G80", "M9", "M30", "%"]

    {:ok, _} = Library.store(lib, "77", Program.to_text(lines), source: "cli")
    # a draft after it: never drip-fed, the released version 1 is the latest
    {:ok, _} =
      Library.store(lib, "77", Program.to_text(lines ++ ["%"]), source: "cli", state: :draft)

    # restarted at line 200 (N194): the preamble printed before the first block, the machine runs
    # exactly the restarted program
    {:ok, preamble, restarted} = NCModal.restart(lines, 200)
    assert preamble == ["G21 G17 G90 G54", "T3 M6", "S1500 M3", "M8", "G01 F300"]
    sent = Program.to_text(restarted)

    args =
      ~w(--program 77 --line 200 --library #{library} --baud 96000 --memory 2048 --feed-rate 600)

    proc = Acceptance.start(["mix", "vws.drip_feed" | args], env: [{"MIX_ENV", "dev"}])
    on_exit(fn -> Acceptance.stop(proc) end)
    assert Acceptance.await_exit(proc, 120_000) == 0, Acceptance.output(proc)
    output = Acceptance.output(proc)

    shown =
      "000077.PRO version 1 restarted at line 200; sent before it, restoring the modal state " <>
        "of lines 1-199:\n  %\n  O77\n  (RESTART AT LINE 200)\n  G21 G17 G90 G54\n  T3 M6\n" <>
        "  S1500 M3\n  M8\n  G01 F300\n"

    assert [earlier, later] = String.split(output, shown, parts: 2), output
    refute earlier =~ "drip feed of"
    assert later =~ "drip feed of 000077.PRO: #{byte_size(sent)} bytes"
    crc = Integer.to_string(Vws.Codecs.CRC16.compute(sent), 16)

    assert output =~
             ~r/received #{byte_size(sent)} bytes, ran #{byte_size(sent)}, .* 0 underruns, CRC #{crc}, state done/

    # refused in the WC's words, nothing sent: a draft, a line inside the canned cycle
    for {extra, words} <- [
          {~w(--version 2), "000077.PRO: ERROR 000077.PRO VERSION 2 NOT RELEASED (nothing sent)"},
          {~w(--line #{length(lines) - 3}),
           "ERROR RESTART LINE #{length(lines) - 3} INSIDE A CANNED CYCLE G81 (NO G80 BEFORE IT)"}
        ] do
      proc =
        Acceptance.start(
          ["mix", "vws.drip_feed", "--program", "000077.PRO", "--library", library | extra],
          env: [{"MIX_ENV", "dev"}]
        )

      assert Acceptance.await_exit(proc, 60_000) == 1
      output = Acceptance.output(proc)
      assert output =~ words
      refute output =~ "drip feed of"
    end
  end

  test "mix vws.drip_feed --program: a long library program (1.5 MB, over the 999,999 bytes the " <>
         "machine stores, well within what the library keeps) through an 8 KiB buffer",
       %{tmp_dir: dir} do
    library = Path.join(dir, "library")
    # 1,500,024 bytes: over what the machine stores (Vws.Test.MonarchWC.long_program/1)
    text = Vws.Test.MonarchWC.long_program(88)
    assert byte_size(text) == 1_500_024
    assert byte_size(text) > Program.max_stored_bytes() and byte_size(text) <= Library.max_bytes()
    {:ok, v} = Library.store({:dir, library}, "88", text, source: "cli")
    # its file name carries a seven-digit size (libraries written before keep six-digit names)
    assert v.file =~ "~1500024~"

    args = ~w(--program 88 --library #{library} --memory 8192 --feed-rate 5000000)
    proc = Acceptance.start(["mix", "vws.drip_feed" | args], env: [{"MIX_ENV", "dev"}])
    on_exit(fn -> Acceptance.stop(proc) end)
    assert Acceptance.await_exit(proc, 300_000) == 0, Acceptance.output(proc)
    output = Acceptance.output(proc)
    assert output =~ "000088.PRO version 1 from the library"
    assert output =~ "drip feed of 000088.PRO: 1500024 bytes"
    crc = Integer.to_string(Vws.Codecs.CRC16.compute(text), 16)

    assert output =~
             ~r/received #{byte_size(text)} bytes, ran #{byte_size(text)}, buffer \d+\/8192 at most, .* CRC #{crc}, state done/

    # byte for byte: the SHA-256 of what the machine received is the library version's
    assert output =~ "SHA-256 #{v.digest}"
    assert v.digest == Library.digest(text)
  end
end
