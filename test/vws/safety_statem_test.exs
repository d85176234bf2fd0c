defmodule Vws.SafetyStatemTest do
  @moduledoc false
  # Stateful safety test (issue 6): random sequences of WC commands for every partition, moves of
  # the material-handling system and injected faults, against the real partitions and simulators
  # (Vws.Test.SafetyModel, Vws.Test.SafetyFloor). The plant's collision oracle must record
  # nothing; every command must end DONE or ERROR with a reason, none stay EXECUTING.
  # bench/safety_soak.exs runs the same model for 10 000 sequences.
  # Not async: it keeps two cores busy for half a minute, and the timing tests of the other
  # modules should not have to share them with it.
  use ExUnit.Case, async: false
  use Vws.PropCase

  alias Vws.Test.SafetyModel

  @moduletag timeout: 300_000
  @sequences 300

  test "no collision, and every command ends, over #{@sequences} random sequences" do
    property =
      :proper.forall(SafetyModel.commands(), fn cmds ->
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

    assert_property(property, @sequences)
  end
end
