# What the dashboard's MTConnect agent costs per VWS_STATUS poll (issue 29): the web server (and
# its agent) runs by default beside the workstations (`mix vws.serve`, the release), and the agent
# records every change a poll writes to the mailbox. This runs the demo's floors with the web on
# and counts, over --seconds, the reductions of the agent, the state snapshot and VWS_STATUS per
# poll (reductions: the BEAM's own measure of work, which other load on the machine does not
# change), and which mailbox changes came per poll.
#
#     mix run bench/agent_cost.exs [--workstations 1] [--seconds 10]
#
# Figures (2026-11-27, session ten, one workstation, load 3–4; the two lib files of the commit
# before checked out for the "before"): the agent 3,356 reductions per poll when every change
# observed the workstation's 54 data items again, 325 once a poll's changes (SENSORS every poll,
# VISE's text 0.61 times a poll: its force) record their few items alone
# (Vws.Ops.MTConnect.Model.changed_values/3); VWS_STATUS's own 983–986.

Code.require_file("support.exs", __DIR__)
Logger.configure(level: :error)

alias Vws.Bench

{opts, _, _} =
  OptionParser.parse(System.argv(), strict: [workstations: :integer, seconds: :integer])

n = Keyword.get(opts, :workstations, 1)
seconds = Keyword.get(opts, :seconds, 10)
ids = for i <- 1..n, do: "AGENT-COST-#{i}"

for id <- ids, do: {:ok, _} = Vws.Ops.Demo.start_shop_floor(id: id, time_scale: 1)
{:ok, web} = Vws.Ops.Web.start_link(port: 0)

children =
  Map.new(Supervisor.which_children(web), fn {_id, child, _, [module]} -> {module, child} end)

agent = children[Vws.Ops.MTConnect.Agent]
snapshot = children[Vws.Ops.Web.Snapshot]
vws_status = for id <- ids, do: GenServer.whereis(Vws.CEC.Partition.via(id, :vws_status))

Process.sleep(3_000)
for id <- ids, do: :ok = Vws.CEC.Events.subscribe(id, :mailbox)

reductions = fn pids ->
  Enum.sum(for p <- pids, do: p |> Process.info(:reductions) |> elem(1))
end

polls = fn -> Enum.sum(for id <- ids, do: Vws.Partitions.VwsStatus.stats(id).polls) end

p0 = polls.()
r0 = {reductions.([agent]), reductions.([snapshot]), reductions.(vws_status)}
deadline = System.monotonic_time(:millisecond) + seconds * 1_000

tally = fn tally, acc ->
  receive do
    {:vws_event, _, :mailbox, {change, _}} ->
      key =
        case change do
          {:device, loc, _} -> Vws.CEC.Mailbox.device_name(loc)
          other -> elem(other, 0)
        end

      tally.(tally, Map.update(acc, key, 1, &(&1 + 1)))
  after
    max(deadline - System.monotonic_time(:millisecond), 0) -> acc
  end
end

changes = tally.(tally, %{})
done = polls.() - p0
{a0, s0, v0} = r0
per = fn r1, r0 -> div(r1 - r0, max(done, 1)) end

IO.puts("""
The MTConnect agent's cost per VWS_STATUS poll (bench/agent_cost.exs)
#{Enum.join(Bench.machine(), "\n")}
  workstations   #{n}, #{seconds} s, #{done} polls
  reductions     per poll: the agent #{per.(reductions.([agent]), a0)}, the state snapshot #{per.(reductions.([snapshot]), s0)}, VWS_STATUS #{per.(reductions.(vws_status), v0)}
  changes        per poll: #{Enum.map_join(Enum.sort(changes), ", ", fn {k, c} -> "#{k} #{Float.round(c / max(done, 1), 2)}" end)}
""")
