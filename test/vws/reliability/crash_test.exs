# Issue 8's crash campaign (Vws.Test.CrashCampaign): every link and partition process of a
# workstation killed 100 times at random moments while a WC runs the machining cycle over and
# over. The thirteen targets are shared among @groups modules, each with its own workstation and
# floor and its links and partitions killed side by side, so that the campaigns run at once.
groups = 7

for group <- 0..(groups - 1) do
  defmodule Module.concat(Vws.Reliability.CrashTest, "Group#{group + 1}") do
    use ExUnit.Case, async: true

    alias Vws.Test.CrashCampaign

    @moduletag timeout: 300_000
    @share {group, groups}

    setup do
      CrashCampaign.setup_cell()
    end

    test "links and partitions of share #{group + 1}/#{groups} killed 100 times each during cycles",
         ctx do
      CrashCampaign.run(ctx, @share)
    end
  end
end
