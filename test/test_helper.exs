# Every test run has a temporary directory of its own (TMPDIR, inherited by the OS processes the
# tests start): paths made from System.unique_integer/1 repeat from one VM to the next, and two
# runs on one host (two clones, a developer and CI) removed each other's release and files.
run_tmp = Path.join(System.tmp_dir!(), "vws-test-run-#{System.pid()}")
File.rm_rf!(run_tmp)
File.mkdir_p!(run_tmp)
System.put_env("TMPDIR", run_tmp)
ExUnit.after_suite(fn _ -> File.rm_rf(run_tmp) end)

# assert_receive waits up to 2 s by default: a loaded CI machine must not fail a correct test.
#
# max_cases: the suite waits far more than it computes — about 900 s of test time for about 120 s
# of CPU — on simulated floors, timeouts and OS processes, so async modules run 8 per scheduler
# (16 on a 2-core machine) rather than ExUnit's 2. The long campaigns are split into modules
# (crash campaign, DNC bit flips, the stateful safety test) so that they overlap too. The
# simulated instruments (Vws.Sim.DAQ, Vws.Sim.Plant) and the HPIB bus run at high process
# priority, as equipment with its own processor would: at normal priority, this much
# concurrency made DAQ answers 300 ms late.
ExUnit.start(
  capture_log: true,
  assert_receive_timeout: 2_000,
  max_cases: System.schedulers_online() * 8
)

# The longest async modules first (test/module_seconds.txt, Vws.Test.ModuleOrder): run as their
# files loaded, the longest of them started late and ended the async phase alone.
ExUnit.configure(formatters: [Vws.Test.ModuleOrder | ExUnit.configuration()[:formatters]])

# The failed tests are named again after the summary, without their captured logs
# (Vws.Test.FailureRecap): one failure's log is hundreds of lines, and a CI page that shows only
# the end of the output showed the count of failures without their names.
ExUnit.configure(formatters: ExUnit.configuration()[:formatters] ++ [Vws.Test.FailureRecap])
ExUnit.after_suite(fn _ -> Vws.Test.FailureRecap.recap() end)

if System.get_env("VWS_MODULE_SECONDS") == "write" do
  ExUnit.configure(
    formatters: ExUnit.configuration()[:formatters] ++ [Vws.Test.ModuleOrder.Recorder]
  )
end

# Tests that need what this host may not have are excluded by their tag, saying why.
exclude = fn tag, why ->
  IO.puts("Excluding the tests tagged #{inspect(tag)}: #{why}")
  ExUnit.configure(exclude: Enum.uniq(ExUnit.configuration()[:exclude] ++ [tag]))
end

# The tests validating MTConnect documents against the official schemas (tag :mtconnect_schemas)
# need them beside the project (../shared/mtconnect) or in $VWS_MTCONNECT_SCHEMAS (Vws.Test.XMLLint).
if reason = Vws.Test.XMLLint.missing_schemas(), do: exclude.(:mtconnect_schemas, reason)

# The tests tagged :ipv6 bind the IPv6 loopback, which a container may not have.
case :gen_tcp.listen(0, [:inet6, ip: {0, 0, 0, 0, 0, 0, 0, 1}]) do
  {:ok, socket} ->
    :gen_tcp.close(socket)

  {:error, reason} ->
    exclude.(:ipv6, "no IPv6 loopback here (#{inspect(reason)})")
end

# The suite leaves no daemon running: an epmd started by a test (distribution) is stopped after it.
Vws.Test.Acceptance.stop_epmd_after_suite()

# The acceptance tests (tag :acceptance) start `mix` (MIX_ENV=dev) and the release (MIX_ENV=prod)
# as OS processes. Their builds are made here, before any test runs, when this run includes them:
# made by the first test that needed them, they took both cores for up to a minute in the middle
# of the async phase and starved the simulated floors (DAQ #1 not answering in 300 ms).
{opts, paths, _} =
  OptionParser.parse(Enum.drop(System.argv(), 1),
    switches: [exclude: :keep, include: :keep, only: :keep, formatter: :keep, seed: :integer]
  )

acceptance? =
  "acceptance" not in Keyword.get_values(opts, :exclude) and
    (paths == [] or Enum.any?(paths, &(&1 =~ ~r{(^|/)test/acceptance|release_test})))

if acceptance? do
  Vws.Test.Acceptance.prebuild("dev")
  Vws.Test.Acceptance.release()
end
