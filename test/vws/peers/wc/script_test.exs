defmodule Vws.Codecs.WC.ScriptTest do
  use ExUnit.Case, async: true

  alias Vws.Peers.WC.{Script, ScriptError}

  doctest Vws.Peers.WC.Script
  doctest Vws.Peers.WC.ScriptError

  @tag :tmp_dir
  test "golden: every kind of step, comments and blank lines", %{tmp_dir: dir} do
    File.mkdir_p!(Path.join(dir, "programs"))
    File.write!(Path.join(dir, "programs/p.nc"), "%\r\nO000001\r\nN10 G00 X0\r\n%\r\n\r\n")

    text = """
    # a comment line
       # an indented comment

    r do move SAFE                        # trailing comment
    R DO MOVE MV1:TRANS(63.5,0,0,90,-90,0) & G OPEN
    status trays
    EXPECT TRAYS TRAY #1 IN POSITION  # '#1' is text
    EXPECT vise   vise is   unlocked
    EXPECT GRIPPER ~ FINGERS ARE \\d+(\\.\\d+)? MM APART
    WAIT MONARCH IDLE
    DOWNLOAD programs/p.nc
    UPLOAD
    TIMEOUT 1.5
    M PROGRAM_SELECT(000001)
    """

    assert {:ok, %Script{steps: steps}} = Script.parse(text, base_dir: dir)

    assert [
             {4, "r do move SAFE", {:commands, [{"R", "do move SAFE"}]}},
             {5, _, {:commands, [{"R", "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"}, {"G", "OPEN"}]}},
             {6, _, {:status, "TRAYS"}},
             {7, "EXPECT TRAYS TRAY #1 IN POSITION",
              {:expect, "TRAYS", {:prefix, "TRAY #1 IN POSITION"}}},
             {8, _, {:expect, "VISE", {:prefix, "VISE IS UNLOCKED"}}},
             {9, _, {:expect, "GRIPPER", {:regex, regex}}},
             {10, _, {:wait, "MONARCH", {:prefix, "IDLE"}}},
             {11, _, {:download, path, ["%", "O000001", "N10 G00 X0", "%"]}},
             {12, _, :upload},
             {13, _, {:timeout, 1500}},
             {14, _, {:commands, [{"M", "PROGRAM_SELECT(000001)"}]}}
           ] = Enum.map(steps, &{&1.line, &1.source, &1.op})

    assert Regex.source(regex) == "FINGERS ARE \\d+(\\.\\d+)? MM APART"
    assert path == Path.join(dir, "programs/p.nc")
  end

  test "matchers: prefix in upper case with blanks collapsed, or a regex" do
    assert Script.matches?({:prefix, "VISE IS UNLOCKED"}, "vise is unlocked part not in vise")
    refute Script.matches?({:prefix, "VISE IS UNLOCKED"}, "NO DATA (NO LINK TO DAQ #1)")
    assert Script.matches?({:regex, ~r/LOCKED PART IN VISE$/}, "VISE IS LOCKED PART IN VISE")
  end

  test "the shipped scripts parse" do
    for file <- ["table1.vws", "machining_cycle.vws"] do
      assert {:ok, %Script{steps: [_ | _]}} = Script.parse_file(Path.join("priv/sims", file)),
             file
    end
  end

  test "Table 1's seed steps come first, string for string" do
    {:ok, script} = Script.parse_file("priv/sims/table1.vws")
    [step1, step4 | _] = script.steps

    assert step1.op ==
             {:commands, [{"R", "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)"}, {"G", "OPEN"}]}

    assert step4.op == {:commands, [{"R", "DISABLE_TRAY1"}]}
  end

  test "the machining cycle does all its stages" do
    {:ok, script} = Script.parse_file("priv/sims/machining_cycle.vws")
    ops = Enum.map(script.steps, & &1.op)
    commands = for {:commands, cs} <- ops, c <- cs, do: c

    stages = [
      {"R", "DO MOVES TRAY1"},
      {"G", "CLOSE"},
      {"R", "DO MOVES VISE"},
      {"F", "CLOSE"},
      {"M", "DOWNLOAD_GE"},
      {"M", "PROGRAM_SELECT(001234)"},
      {"M", "CYCLE_START"},
      {"F", "OPEN"},
      {"R", "DO MOVES TRAY1"},
      {"G", "OPEN"}
    ]

    assert subsequence?(stages, commands)
    assert Enum.any?(ops, &match?({:download, _, ["%", "O001234" | _]}, &1))
    assert Enum.any?(ops, &match?({:wait, "MONARCH", {:prefix, "IDLE"}}, &1))
  end

  defp subsequence?([], _), do: true
  defp subsequence?(_, []), do: false
  defp subsequence?([x | xs], [x | ys]), do: subsequence?(xs, ys)
  defp subsequence?(xs, [_ | ys]), do: subsequence?(xs, ys)

  describe "errors name the line" do
    defp error(text, opts \\ []) do
      assert {:error, %ScriptError{} = e} = Script.parse(text, [path: "t.vws"] ++ opts)
      {e.reason, e.line, Exception.message(e)}
    end

    test "unknown step, unknown set, repeated set" do
      assert {:unknown_step, 2, "t.vws:2: \"MOVE SAFE\" is not a step" <> _} =
               error("# ok\nMOVE SAFE\n")

      assert {:bad_command_set, 1, _} = error("S ROBOT_CMD")
      assert {:bad_command_set, 1, _} = error("A 0054")

      assert {:repeated_set, 3, "t.vws:3: set R appears twice" <> _} =
               error("\n\nR DO MOVE SAFE & R DO MOVE VISE")
    end

    test "commands are checked against their set" do
      assert {:bad_command, 1, msg} = error("G OPN")
      assert msg =~ "G OPN: not a command of the gripper set"
      assert {:bad_command, 1, msg} = error("M TABLE(3/1)")
      assert msg =~ "TABLE LINES MUST BE ASCENDING"
      assert {:bad_command, 1, _} = error("F OPEN*")
      assert {:missing_argument, 1, _} = error("R")
      assert {:transfer_command, 1, msg} = error("M DOWNLOAD_HP")
      assert msg =~ "DOWNLOAD <file>"
      assert {:transfer_command, 1, _} = error("M UPLOAD_SUN")
    end

    test "status names, matchers and numbers" do
      assert {:unknown_status, 1, msg} = error("EXPECT VISSE OPEN")
      assert msg =~ "\"VISSE\" is not a status"
      assert {:missing_argument, 1, _} = error("EXPECT VISE")
      assert {:missing_argument, 1, _} = error("WAIT")
      assert {:missing_argument, 1, _} = error("STATUS")
      assert {:missing_argument, 1, _} = error("STATUS VISE TRAYS")
      assert {:missing_argument, 1, _} = error("UPLOAD now")
      assert {:bad_regex, 1, _} = error("EXPECT VISE ~ (unclosed")
      assert {:missing_argument, 1, _} = error("EXPECT VISE ~")
      assert {:bad_number, 1, _} = error("TIMEOUT soon")
      assert {:bad_number, 1, _} = error("TIMEOUT 0")
    end

    @tag :tmp_dir
    test "programs are read and checked when the script is", %{tmp_dir: dir} do
      assert {:program_unreadable, 1, msg} = error("DOWNLOAD nope.nc", base_dir: dir)
      assert msg =~ "cannot read the NC program nope.nc"

      File.write!(Path.join(dir, "open.nc"), "%\nO1\nN10 G00\n")
      assert {:bad_program, 2, msg} = error("\nDOWNLOAD open.nc", base_dir: dir)
      assert msg =~ "the last line must be %"

      File.write!(Path.join(dir, "mid.nc"), "O1\n%\nN10\n%\n")
      assert {:bad_program, 1, msg} = error("DOWNLOAD mid.nc", base_dir: dir)
      assert msg =~ "line 2 is a %"

      File.write!(Path.join(dir, "tab.nc"), "O1\n\tN10\n%\n")
      assert {:bad_program, 1, _} = error("DOWNLOAD tab.nc", base_dir: dir)
    end

    test "an empty script and a missing file" do
      assert {:error, %ScriptError{reason: :empty}} = Script.parse("# nothing\n\n")

      assert {:error, %ScriptError{reason: :unreadable, file: "no/such.vws"} = e} =
               Script.parse_file("no/such.vws")

      assert Exception.message(e) =~ "no/such.vws: cannot read the script"
    end
  end
end
