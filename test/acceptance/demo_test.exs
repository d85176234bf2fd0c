defmodule Vws.Acceptance.DemoTest do
  # `mix vws.demo --once --ber 1e-4 --seed N` as the README runs it: a real OS process whose
  # dialogue shows damaged bytes readably and which ends with its summary and exit status —
  # seed 3 crashed at its step 34 on a damaged byte reaching IO.puts.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag timeout: 300_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  test "mix vws.demo --once --ber 1e-4 --seed 3 runs to its summary; exit 0 only if it completed" do
    proc =
      Acceptance.start(
        ~w(mix vws.demo --once --ber 1e-4 --seed 3 --time-scale 20 --http-port 0),
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    status = Acceptance.await_exit(proc, 240_000)
    output = Acceptance.output(proc)

    assert output =~ "faulty lines (Vws.Sim.Line) on the links:"
    assert output =~ "== Summary ==", output
    refute output =~ ~r/\*\* \(|SUPERVISOR REPORT|CRASH REPORT/, output
    assert String.valid?(output)
    assert [result] = Regex.run(~r/^result: +(.*)$/m, output, capture: :all_but_first)

    if result == "COMPLETED",
      do: assert(status == 0, output),
      else: assert(status != 0 and result =~ ~r/^STOPPED at line \d+ \(step \d+ of \d+\): \S/)
  end
end
