defmodule Vws.Peers.WC.PrinterTest do
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO
  alias Vws.Peers.WC.Client.Event
  alias Vws.Peers.WC.Printer

  doctest Printer

  # `mix vws.demo --ber 1e-4 --seed 3` stopped at its step 34: a reply with a flipped bit
  # (0xD6, not UTF-8) reached IO.puts, which raised
  test "a line damaged on the wire is printed with its damaged bytes as \\xNN, not a crash" do
    damaged = "11S0090ACTI" <> <<0xD6>> <> "E058"

    query = %Event{
      at: 5874,
      direction: :sent,
      kind: :status_query,
      line: "*0114*S0090MONARCH*104",
      meaning: "ask MONARCH"
    }

    answer = %Event{
      at: 5876,
      direction: :received,
      kind: :status,
      line: damaged,
      meaning: "MONARCH: ACTI" <> <<0xD6>> <> "E"
    }

    output =
      capture_io(fn ->
        printer = Printer.print_event(query, Printer.new())
        Printer.print_event(answer, printer)
      end)

    assert output =~ ~r/^ +5\.876s  ← 11S0090ACTI\\xD6E058 +MONARCH: ACTI\\xD6E$/m
    assert String.valid?(output)
  end

  test "a status asked again with the same answer is folded into one row" do
    events =
      for {at, i} <- Enum.with_index([0, 10, 20, 30]), dir <- [:sent, :received] do
        if dir == :sent,
          do: %Event{
            at: at,
            direction: :sent,
            kind: :status_query,
            line: "*000#{i}*S000#{i}ROBOT_CMD*000",
            meaning: "ask ROBOT_CMD"
          },
          else: %Event{
            at: at + 1,
            direction: :received,
            kind: :status,
            line: "13S000#{i}0001EXECUTING000",
            meaning: "ROBOT 0001 EXECUTING"
          }
      end

    done = %Event{
      at: 45,
      direction: :received,
      kind: :status,
      line: "x",
      meaning: "ROBOT 0001 DONE"
    }

    query = %Event{
      at: 44,
      direction: :sent,
      kind: :status_query,
      line: "q",
      meaning: "ask ROBOT_CMD"
    }

    output =
      capture_io(fn ->
        Enum.reduce(
          events ++ [query, done],
          Printer.new(),
          &Printer.print_event/2
        )
      end)

    assert [q0, a0, folded, q4, a4] = String.split(output, "\n", trim: true)
    assert q0 =~ "→ *0000*S0000ROBOT_CMD*000"
    assert a0 =~ "ROBOT 0001 EXECUTING"
    assert folded =~ "… asked 3 more times over 0.021s: same answer"
    assert q4 =~ "ask ROBOT_CMD"
    assert a4 =~ "ROBOT 0001 DONE"
  end
end
