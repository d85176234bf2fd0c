defmodule Vws.CEC.Interlock.RulesTableTest do
  @moduledoc false
  # The interlock table covers every command of every set: walked from the command sets
  # themselves (Vws.Codecs.Commands.kinds/0), so a command added to a set without a rule fails
  # here — and, at run time, is refused (an interlock that cannot be decided denies).
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.CEC.Interlock.Rules
  alias Vws.Codecs.Commands

  doctest Rules

  test "every kind of every set parses from its example and has a rule" do
    for {partition, kinds} <- Commands.kinds(), {kind, text} <- kinds do
      assert {:ok, command} = Commands.parse(partition, text), "#{partition} #{text}"
      assert Rules.kind(command) == kind, "#{partition} #{text}"
      assert {:ok, _rule} = Rules.rule(partition, command), "#{partition} #{kind} has no rule"
    end
  end

  test "the six sets are all there, with the commands we added beyond the seed" do
    kinds = Commands.kinds()

    assert Map.keys(kinds) |> Enum.sort() ==
             Enum.sort([:robot, :monarch, :gripper, :fixture, :vacuum, :hydraulic])

    for kind <- [:drip_feed, :compare_ge, :download_ge, :upload_ge, :cycle_start],
        do: assert(Keyword.has_key?(kinds.monarch, kind))
  end

  test "every command that starts the machine takes the table from the robot and the vise" do
    for {kind, _text} <- Commands.kinds().monarch,
        {:ok, %{take: :table} = rule} <- [Rules.rule(:monarch, kind)] do
      assert rule.as == :cycle
      assert rule.on_error == :keep
      # the table's two CEC users may share it with each other, never with the machine
      refute Vws.CEC.Interlock.compatible?(:table, :monarch, :robot)
      refute Vws.CEC.Interlock.compatible?(:table, :monarch, :fixture)
    end

    assert {:ok, %{take: :table, as: :cycle}} = Rules.rule(:monarch, :drip_feed)
    assert {:ok, %{take: :table, as: :cycle}} = Rules.rule(:monarch, :cycle_start)
  end

  test "a command kind the table does not know is refused in words" do
    assert Rules.rule(:monarch, :launch_missiles) ==
             {:error, "NO INTERLOCK RULE FOR MONARCH LAUNCH_MISSILES"}

    assert Rules.rule(:robot, {:teleport, "VISE"}) ==
             {:error, "NO INTERLOCK RULE FOR ROBOT TELEPORT"}
  end

  test "every parsed command of a generated text has a rule (many texts per set)" do
    texts =
      for {partition, kinds} <- Commands.kinds(), {_kind, text} <- kinds, do: {partition, text}

    property =
      :proper.forall(
        {:proper_types.oneof(texts), :proper_types.oneof([" ", "", "  "]), :proper_types.bool()},
        fn {{partition, text}, pad, lower} ->
          text = if lower, do: String.downcase(text), else: text

          case Commands.parse(partition, pad <> text <> pad) do
            {:ok, command} -> match?({:ok, _}, Rules.rule(partition, command))
            {:error, _} -> true
          end
        end
      )

    assert_property(property, 300)
  end
end
