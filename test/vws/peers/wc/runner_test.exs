defmodule Vws.Codecs.WC.RunnerTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.Mailbox
  alias Vws.Peers.WC.{Client, ClientError, Runner, Script}
  alias Vws.Peers.WC.Runner.Summary
  alias Vws.Test.{ObedientPartition, Workstation}

  doctest Vws.Peers.WC.Runner.Summary

  defp script!(text, opts \\ []) do
    {:ok, script} = Script.parse(text, opts)
    script
  end

  test "on a workstation without device links, a cycle stops at its first command with NO LINK" do
    %{wc: wc} = Workstation.start()
    {:ok, client} = Client.connect(wc)
    {:ok, script} = Script.parse_file("priv/sims/machining_cycle.vws")
    [first | _] = script.steps

    summary = Runner.run(client, script, poll_interval: 5)

    assert %Summary{result: :stopped, steps_done: 0, commands: 1} = summary
    assert summary.stopped.line == first.line
    assert summary.stopped.step == 1
    assert summary.stopped.reason == "ROBOT command 0001 ended ERROR NO LINK TO VAL II"
    assert %ClientError{reason: :command_failed} = summary.stopped.error
    refute Summary.completed?(summary)

    assert Enum.at(Summary.format(summary), 1) ==
             "result:          STOPPED at line #{first.line} (step 1 of #{length(script.steps)}): " <>
               "ROBOT command 0001 ended ERROR NO LINK TO VAL II"

    notes = for %{direction: :note, meaning: m} <- Client.log(client), do: m
    assert hd(notes) =~ "step 1 of #{length(script.steps)}, line #{first.line}: R DISABLE_TRAY1"
  end

  test "the Table 1 task stops the same way, at the robot's move" do
    %{wc: wc} = Workstation.start()
    {:ok, client} = Client.connect(wc)
    {:ok, script} = Script.parse_file("priv/sims/table1.vws")
    summary = Runner.run(client, script, poll_interval: 5)
    assert summary.stopped.reason == "ROBOT command 0001 ended ERROR NO LINK TO VAL II"
    # the robot's status was asked next, as in the seed's step 2 (again while it was EXECUTING)
    [_string, first_query | more] = for(%{direction: :sent, line: l} <- Client.log(client), do: l)
    assert first_query =~ ~r/^\*0002\*S0001ROBOT_CMD\*/
    assert Enum.all?(more, &(&1 =~ ~r/^\*\d{4}\*S\d{4}ROBOT_CMD\*/))
  end

  @tag :tmp_dir
  test "a script runs to its end when every step succeeds", %{tmp_dir: dir} do
    %{ws: ws, wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
    {:ok, client} = Client.connect(wc)
    File.write!(Path.join(dir, "p.nc"), "%\nO000042\nN10 G00 X0\n%\n")

    Mailbox.put_device(
      ws,
      Mailbox.device_location("GRIPPER"),
      "GRIPPER IS OPEN AND INDEXER ROTATED 90 DEG"
    )

    Mailbox.put_device(ws, Mailbox.device_location("MONARCH"), "IDLE")

    script =
      script!(
        """
        R DO MOVE SAFE & G OPEN
        EXPECT GRIPPER GRIPPER IS OPEN
        EXPECT GRIPPER ~ ROTATED \\d+ DEG$
        STATUS TRAYS
        TIMEOUT 5
        WAIT MONARCH IDLE
        DOWNLOAD p.nc
        M PROGRAM_SELECT(000042)
        """,
        base_dir: dir
      )

    summary = Runner.run(client, script, poll_interval: 5)

    assert %Summary{
             result: :completed,
             stopped: nil,
             steps_total: 8,
             steps_done: 8,
             commands: 4,
             program_lines_sent: 4,
             resends: 0
           } = summary

    assert Summary.completed?(summary)
    assert Enum.at(Summary.format(summary), 1) == "result:          COMPLETED"
    assert Mailbox.nc_file(ws) == ["%", "O000042", "N10 G00 X0", "%"]
  end

  @tag :tmp_dir
  test "a program transfer that broke off on the link is made again as a new command",
       %{tmp_dir: dir} do
    %{ws: ws, wc: wc} = Workstation.start()
    name = "runner-relay-#{System.unique_integer([:positive])}"
    {:ok, relay} = Vws.Test.LineRelay.start_link(wc, name)
    {:ok, client} = Client.connect("loopback:" <> name)
    File.write!(Path.join(dir, "p.nc"), "%\nO000042\nN10 G00 X0\n%\n")
    # the answer to the second program line arrives damaged four times: the line was sent as
    # often as the client sends one (1 + 3 resends), so the transfer breaks off
    :ok = Vws.Test.LineRelay.arm(relay, :to_wc, :corrupt, &String.starts_with?(&1, "A0002"), 4)
    summary = Runner.run(client, script!("DOWNLOAD p.nc\n", base_dir: dir), poll_interval: 5)

    assert %Summary{result: :completed, transfers_broken: 1} = summary
    assert Mailbox.nc_file(ws) == ["%", "O000042", "N10 G00 X0", "%"]
    # the broken one ended ERROR, the new one (number 2) DONE
    assert Mailbox.command_status(ws, :monarch) == {2, :done}
    assert Enum.any?(Summary.format(summary), &(&1 =~ "1 transfers broke off"))

    # with no retries allowed, the script stops at the broken transfer
    :ok = Vws.Test.LineRelay.arm(relay, :to_wc, :corrupt, &String.starts_with?(&1, "A0002"), 4)

    summary =
      Runner.run(client, script!("DOWNLOAD p.nc\n", base_dir: dir),
        poll_interval: 5,
        transfer_retries: 0
      )

    assert %Summary{result: :stopped, transfers_broken: 1} = summary
    assert summary.stopped.reason =~ "broke off"
  end

  @tag :tmp_dir
  test "a program that arrived other than sent (its CRC) is sent again as a new command",
       %{tmp_dir: dir} do
    %{ws: ws, wc: wc} = Workstation.start()
    name = "runner-relay-#{System.unique_integer([:positive])}"
    {:ok, relay} = Vws.Test.LineRelay.start_link(wc, name)
    {:ok, client} = Client.connect("loopback:" <> name)
    File.write!(Path.join(dir, "p.nc"), "%\nO000042\nN10 G00 X0\n%\n")
    # line 3 damaged once on its way so that its BCC still holds: 'G' 0x47 → 'F', '0' → '1'
    damage = &String.replace(&1, "N10 G00 X0", "N10 F01 X0")
    :ok = Vws.Test.LineRelay.arm(relay, :to_cec, {:replace, damage}, &(&1 =~ "N10 G00"))
    summary = Runner.run(client, script!("DOWNLOAD p.nc\n", base_dir: dir), poll_interval: 5)

    assert %Summary{result: :completed, transfers_broken: 1} = summary
    assert Mailbox.nc_file(ws) == ["%", "O000042", "N10 G00 X0", "%"]
    assert Mailbox.command_status(ws, :monarch) == {2, :done}

    notes = for %{kind: :note, meaning: m} <- Client.log(client), do: m
    assert Enum.any?(notes, &(&1 =~ "the transfer is made again"))
  end

  test "a device that did not do it stops the script at its EXPECT" do
    %{wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
    {:ok, client} = Client.connect(wc)
    script = script!("G OPEN\n\nEXPECT GRIPPER GRIPPER IS OPEN\nG CLOSE\n")
    summary = Runner.run(client, script, poll_interval: 5, expect_grace: 30)

    assert %Summary{result: :stopped, steps_done: 1, commands: 1} = summary
    assert summary.stopped.line == 3

    assert summary.stopped.reason ==
             "GRIPPER is \"NO DATA (NO LINK TO DAQ #1)\", expected \"GRIPPER IS OPEN…\""
  end

  test "a WAIT that never matches stops at its timeout; the CEC's reason stops a command" do
    %{wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
    {:ok, client} = Client.connect(wc)

    summary = Runner.run(client, script!("TIMEOUT 0.05\nWAIT MONARCH IDLE"), poll_interval: 5)

    assert summary.stopped.reason =~
             ~r/^MONARCH did not become "IDLE…" within 50 ms; last "NO DATA/

    # not a vacuum command a script would pass: built by hand
    failing = %Script.Step{
      line: 2,
      source: "V FAIL",
      op: {:commands, [{"V", "FAIL VACUUM LINE BROKEN"}]}
    }

    script = %Script{steps: script!("V ON").steps ++ [failing]}
    summary = Runner.run(client, script, poll_interval: 5)
    assert summary.stopped.reason == "VACUUM command 0002 ended ERROR VACUUM LINE BROKEN"
    assert summary.steps_done == 1
  end
end
