# Stateful safety test (issue 6): random sequences of WC commands for every partition, moves of
# the material-handling system and injected faults, against the real partitions and simulators
# (Vws.Test.SafetyModel, Vws.Test.SafetyFloor). The plant's collision oracle must record
# nothing; every command must end DONE or ERROR with a reason, none stay EXECUTING.
# bench/safety_soak.exs runs the same model for 10 000 sequences.
#
# 300 sequences, in six modules of 50 that run at once (each draws its own: PropEr seeds
# every run from the clock). A sequence spends most of its time waiting on its simulated floor
# (the `:fast` timers), not on a core; on a loaded machine more commands end in a timeout, which
# the properties allow.
for part <- 1..6 do
  defmodule Module.concat(Vws.SafetyStatemTest, "Part#{part}") do
    use ExUnit.Case, async: true
    use Vws.PropCase

    alias Vws.Test.SafetyModel

    @moduletag timeout: 300_000
    @sequences 50

    test "no collision, and every command ends, over #{@sequences} random sequences (#{part}/6)" do
      property =
        :proper.forall(SafetyModel.commands(), fn cmds ->
          # (what a sequence raises is shown with the counterexample: checked/1)
          checked(fn ->
            case SafetyModel.run(cmds) do
              :ok ->
                true

              {:failed, report} ->
                IO.puts(
                  "\nsafety sequence failed:\n" <> inspect(report, pretty: true, limit: :infinity)
                )

                false
            end
          end)
        end)

      assert_property(property, @sequences)
    end
  end
end

defmodule Vws.SafetyStatemTest.Coverage do
  use ExUnit.Case, async: true

  # the model generates every kind of every set, so a command we add is in the sequences too
  test "the model's commands cover every kind of every command set" do
    texts = Vws.Test.SafetyModel.texts()

    for {partition, kinds} <- Vws.Codecs.Commands.kinds(), {kind, _example} <- kinds do
      covered =
        Enum.any?(Map.fetch!(texts, partition), fn text ->
          case Vws.Codecs.Commands.parse(partition, text) do
            {:ok, command} -> Vws.CEC.Interlock.Rules.kind(command) == kind
            {:error, _} -> false
          end
        end)

      assert covered, "the safety model never generates #{partition} #{kind}"
    end
  end
end
