defmodule Vws.Acceptance.DripFeedTaskTest do
  # `mix vws.drip_feed` as docs/dnc-drip-feed.md runs it: a real OS process, a program file,
  # the simulated GE-2000 on a paced line; the exit status says whether the program got there.
  use ExUnit.Case, async: true

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
end
