defmodule Vws.LibraryCycleTest do
  @moduledoc """
  The machining cycle (priv/sims/machining_cycle.vws) run with a program from the library
  (issue 18) instead of the WC's download: the workstation's library holds two versions of
  001234.PRO, the cycle sends version 1 by name, checks it with a full read-back and runs it,
  against the whole simulated shop floor.
  """
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.CEC.Library
  alias Vws.Peers.WC.Runner.Summary

  @moduletag timeout: 240_000
  @moduletag :tmp_dir

  test "the machining cycle with DOWNLOAD_GE(001234.PRO/1) and COMPARE_GE(001234.PRO)", %{
    tmp_dir: tmp
  } do
    id = "libcycle-#{System.unique_integer([:positive])}"
    on_exit(fn -> Vws.CEC.Workstation.stop(id) end)
    lib = {:dir, Path.join(tmp, "library")}

    {:ok, %{version: 1}} = Library.import_file(lib, "priv/sims/programs/001234.nc")
    program = File.read!("priv/sims/programs/001234.nc")
    {:ok, %{version: 2}} = Library.store(lib, "1234", "(V2)\n" <> program, source: "iex")

    cycle = File.read!("priv/sims/machining_cycle.vws")
    assert cycle =~ "DOWNLOAD programs/001234.nc\nM DOWNLOAD_GE\n"

    script = Path.join(tmp, "library_cycle.vws")

    File.write!(
      script,
      String.replace(
        cycle,
        "DOWNLOAD programs/001234.nc\nM DOWNLOAD_GE\n",
        "M DOWNLOAD_GE(001234.PRO/1)\nM COMPARE_GE(001234.PRO)\n"
      )
    )

    capture_io(fn ->
      result =
        Vws.Ops.Demo.run(
          id: id,
          wc: "loopback:#{id}",
          script: script,
          library: Path.join(tmp, "library"),
          time_scale: 50,
          poll_interval: 5
        )

      send(self(), {:result, result})
    end)

    assert_received {:result, {:ok, summary, _floor, _client}}
    assert Summary.completed?(summary), "stopped: #{inspect(summary.stopped)}"

    # the machine ran version 1, and holds it: same as v1, not the latest
    {:ok, %{programs: [row]}} = Library.compare(id)
    assert row.on_machine == {:same, 1}
    assert row.latest.version == 2
  end
end
