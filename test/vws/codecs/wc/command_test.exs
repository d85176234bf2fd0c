defmodule Vws.Codecs.WC.CommandTest do
  use ExUnit.Case, async: true

  alias Vws.Codecs.WC.Command

  doctest Command

  @sets [
    {"R", :robot},
    {"M", :monarch},
    {"F", :fixture},
    {"H", :hydraulic},
    {"G", :gripper},
    {"V", :vacuum},
    {"S", :status},
    {"A", :ack}
  ]

  test "the eight command sets of seed §2.3.2 and their letters" do
    for {letter, set} <- @sets do
      assert Command.set_for_letter(letter) == set
      assert Command.letter_for_set(set) == letter
    end
  end

  test "any other uppercase letter is an unknown set, kept for SUN_COMM to judge" do
    for byte <- ?A..?Z, <<byte>> not in Enum.map(@sets, &elem(&1, 0)) do
      assert Command.set_for_letter(<<byte>>) == {:unknown, <<byte>>}
      assert Command.letter_for_set({:unknown, <<byte>>}) == <<byte>>
    end
  end

  test "lowercase letters and longer strings are not set letters" do
    assert_raise FunctionClauseError, fn -> Command.set_for_letter("r") end
    assert_raise FunctionClauseError, fn -> Command.set_for_letter("RR") end
  end

  test "new/3 takes a set or a letter and refuses what could not be sent" do
    assert Command.new("R", 9, "WHERE") == Command.new(:robot, 9, "WHERE")
    assert %Command{set: :ack, text: ""} = Command.new(:ack, 1, "")
    assert_raise ArgumentError, fn -> Command.new(:robot, 9, "") end
    assert_raise ArgumentError, fn -> Command.new(:robot, 9, "A*B") end
    assert_raise ArgumentError, fn -> Command.new(:robot, 9, "A\rB") end
    assert_raise ArgumentError, fn -> Command.new(:robot, 10_000, "WHERE") end
    assert_raise ArgumentError, fn -> Command.new(:robot, -1, "WHERE") end
  end

  test "pad4 writes every number 0-9999 as four digits" do
    for n <- 0..9999 do
      assert Command.pad4(n) == n |> Integer.to_string() |> String.pad_leading(4, "0")
    end

    assert_raise FunctionClauseError, fn -> Command.pad4(10_000) end
  end
end
