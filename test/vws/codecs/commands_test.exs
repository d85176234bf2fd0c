defmodule Vws.Codecs.CommandsTest do
  use ExUnit.Case, async: true
  use Vws.PropCase
  doctest Vws.Codecs.Commands

  import Vws.Codecs.Commands, only: [parse: 2]

  test "the robot set of App. I B" do
    assert parse(:robot, "WHERE") == {:ok, :where}
    assert parse(:robot, "SPEED 50") == {:ok, {:speed, 50.0}}
    assert parse(:robot, "DO APPRO VISE/100") == {:ok, {:do, :appro, "VISE", 100.0}}
    assert parse(:robot, "DO APPROS TRAY1/50.5") == {:ok, {:do, :appros, "TRAY1", 50.5}}
    assert parse(:robot, "DO DEPART 100") == {:ok, {:do, :depart, 100.0}}
    assert parse(:robot, "DO DEPARTS 25") == {:ok, {:do, :departs, 25.0}}
    assert parse(:robot, "DO MOVE SAFE") == {:ok, {:do, :move, "SAFE"}}
    assert parse(:robot, "DO MOVES SAFE") == {:ok, {:do, :moves, "SAFE"}}

    assert parse(:robot, "DO MOVE MV1:TRANS(63.5/0/0/90/-90/0)") ==
             {:ok, {:do, :move, {:trans, "MV1", [63.5, 0.0, 0.0, 90.0, -90.0, 0.0]}}}

    # the seed's OCR form, with a blank after the colon and lower case
    assert parse(:robot, "DO Move MV1: TRANS(63.5,0,0,90,-90,0)") ==
             {:ok, {:do, :move, {:trans, "MV1", [63.5, 0.0, 0.0, 90.0, -90.0, 0.0]}}}

    assert parse(:robot, "DISABLE_TRAY1") == {:ok, {:disable_tray, 1}}
    assert parse(:robot, "RELEASE_TRAY2") == {:ok, {:release_tray, 2}}
    assert parse(:robot, "DISABLE_TRAY3") == {:error, :unknown}
    assert parse(:robot, "EXECUTE PATH1") == {:ok, {:execute, "PATH1"}}
    assert parse(:robot, "SPEED -3") == {:error, "BAD SPEED -3"}
    assert parse(:robot, "DO MOVE MV1:TRANS(1,2)") == {:error, "BAD TRANS 1,2"}
    assert parse(:robot, "DO FLY") == {:error, :unknown}
  end

  test "DOWNLOAD_GE of a library version, and FORCE for a draft (ours, issues 18 and 27)" do
    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO)") ==
             {:ok, {:download_ge, "004321.PRO", :latest}}

    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO/7)") == {:ok, {:download_ge, "004321.PRO", 7}}

    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO/7/FORCE)") ==
             {:ok, {:download_ge, "004321.PRO", {:force, 7}}}

    assert parse(:monarch, "download_ge(004321.pro/7/force)") ==
             {:ok, {:download_ge, "004321.PRO", {:force, 7}}}

    # FORCE names a version: never "the latest", never anything else
    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO/FORCE)") == {:error, "BAD VERSION FORCE"}
    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO/0/FORCE)") == {:error, "BAD VERSION 0"}

    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO/7/FORCE/X)") ==
             {:error, "BAD PROGRAM FILE 004321.PRO/7/FORCE/X"}

    assert parse(:monarch, "DOWNLOAD_GE(004321.PRO/7/NOW)") ==
             {:error, "BAD PROGRAM FILE 004321.PRO/7/NOW"}
  end

  test "the Monarch set of App. I A" do
    assert parse(:monarch, "CYCLE_START") == {:ok, :cycle_start}
    assert parse(:monarch, "UPLOAD_GE(001234.PRO)") == {:ok, {:upload_ge, "001234.PRO"}}
    assert parse(:monarch, "UPLOAD_GE(001234.GSU)") == {:ok, {:upload_ge, "001234.GSU"}}
    assert parse(:monarch, "UPLOAD_GE(1234.PRO)") == {:error, "BAD PROGRAM FILE 1234.PRO"}
    assert parse(:monarch, "PROGRAM_SELECT(001234)") == {:ok, {:program_select, "001234"}}
    assert parse(:monarch, "PROGRAM_DELETE(001234.PRO)") == {:ok, {:program_delete, "001234.PRO"}}
    assert parse(:monarch, "TABLE(1/3/7)") == {:ok, {:table, [1, 3, 7]}}
    assert parse(:monarch, "TABLE(1/2/3/4/5/6/7/8/9)") == {:error, "AT MOST 8 TABLE LINES"}
    assert parse(:monarch, "TABLE(2/2)") == {:error, "TABLE LINES MUST BE ASCENDING"}
    assert parse(:monarch, "DOWNLOAD_HP") == {:ok, :download_hp}
  end

  test "DOWNLOAD_HP(cccc): the WC names the program's CRC (PROTOCOLS.md §1 Whole-program check)" do
    alias Vws.Codecs.Commands

    assert parse(:monarch, "DOWNLOAD_HP(52D5)") == {:ok, {:download_hp, 0x52D5}}
    assert parse(:monarch, "DOWNLOAD_HP(0000)") == {:ok, {:download_hp, 0}}
    assert parse(:monarch, " download_hp( ffff ) ") == {:ok, {:download_hp, 0xFFFF}}
    assert parse(:monarch, "DOWNLOAD_HP(52D)") == {:error, "BAD PROGRAM CRC 52D"}
    assert parse(:monarch, "DOWNLOAD_HP(52D5A)") == {:error, "BAD PROGRAM CRC 52D5A"}
    assert parse(:monarch, "DOWNLOAD_HP(G2D5)") == {:error, "BAD PROGRAM CRC G2D5"}
    assert parse(:monarch, "DOWNLOAD_HP()") == {:error, "BAD PROGRAM CRC"}
    # what the WC wrote is shown in words (an ERROR text, PROTOCOLS.md §1)
    assert parse(:monarch, ~S|DOWNLOAD_HP("A")|) == {:error, "BAD PROGRAM CRC A"}
    assert parse(:monarch, "DOWNLOAD_HPX") == {:error, :unknown}

    # what SUN_COMM carries out itself, and nothing else
    assert Commands.transfer("DOWNLOAD_HP") == :download_hp
    assert Commands.transfer("DOWNLOAD_HP(52D5)") == {:download_hp, 0x52D5}
    assert Commands.transfer("DOWNLOAD_HP(52D)") == {:error, "BAD PROGRAM CRC 52D"}
    assert Commands.transfer("DOWNLOAD_HPX") == nil
    assert Commands.transfer("DOWNLOAD_HP 52D5") == nil
    assert Commands.transfer("UPLOAD_SUN") == :upload_sun
    assert Commands.transfer("UPLOAD_SUN(52D5)") == nil
    assert Commands.transfer("DOWNLOAD_GE(001234.PRO)") == nil
  end

  test "property: every CRC named is read back; DOWNLOAD_HP with anything else is not a CRC" do
    alias Vws.Codecs.Commands

    named =
      :proper.forall(:proper_types.range(0, 0xFFFF), fn crc ->
        text = "DOWNLOAD_HP(#{Vws.Codecs.WC.ProgramCRC.format(crc)})"

        Commands.transfer(text) == {:download_hp, crc} and
          parse(:monarch, text) == {:ok, {:download_hp, crc}}
      end)

    assert_property(named, 300)

    other =
      :proper.forall(:proper_types.list(:proper_types.range(0x20, 0x7E)), fn chars ->
        arg = List.to_string(chars)
        text = "DOWNLOAD_HP(" <> arg <> ")"

        case Commands.transfer(text) do
          {:download_hp, crc} ->
            String.upcase(String.trim(arg)) == Vws.Codecs.WC.ProgramCRC.format(crc)

          {:error, "BAD PROGRAM CRC" <> _ = why} ->
            Vws.Codecs.WC.Words.text?(why)

          # a ')' or '(' inside: not one parenthesised argument, so not DOWNLOAD_HP
          nil ->
            String.contains?(arg, ["(", ")"])
        end
      end)

    assert_property(other, 300)
  end

  test "DRIP_FEED(nnnnnn.PRO[/v][/Nk]): a library program drip-fed, restarted at line k (issue 27)" do
    assert parse(:monarch, "DRIP_FEED") == {:ok, :drip_feed}

    assert parse(:monarch, "DRIP_FEED(000100.PRO)") ==
             {:ok, {:drip_feed, "000100.PRO", :latest, 1}}

    assert parse(:monarch, "DRIP_FEED(000100.PRO/3)") == {:ok, {:drip_feed, "000100.PRO", 3, 1}}

    assert parse(:monarch, "drip_feed( 000100.PRO/N41000 )") ==
             {:ok, {:drip_feed, "000100.PRO", :latest, 41_000}}

    assert parse(:monarch, "DRIP_FEED(000100.PRO/3/N41000)") ==
             {:ok, {:drip_feed, "000100.PRO", 3, 41_000}}

    assert parse(:monarch, "DRIP_FEED(000100.GSU)") == {:error, "BAD PROGRAM FILE 000100.GSU"}
    assert parse(:monarch, "DRIP_FEED(100.PRO)") == {:error, "BAD PROGRAM FILE 100.PRO"}
    assert parse(:monarch, "DRIP_FEED(000100.PRO/0)") == {:error, "BAD VERSION 0"}
    assert parse(:monarch, "DRIP_FEED(000100.PRO/N0)") == {:error, "BAD RESTART LINE N0"}
    assert parse(:monarch, "DRIP_FEED(000100.PRO/3/N)") == {:error, "BAD RESTART LINE N"}
    assert parse(:monarch, "DRIP_FEED(000100.PRO/3/4)") == {:error, "BAD RESTART LINE 4"}
    assert parse(:monarch, "DRIP_FEED(000100.PRO/3/)") == {:error, "BAD RESTART LINE"}
    assert parse(:monarch, "DRIP_FEED(000100.PRO/)") == {:error, "BAD VERSION"}

    assert parse(:monarch, "DRIP_FEED(000100.PRO/N10000000)") ==
             {:error, "BAD RESTART LINE N10000000"}

    assert parse(:monarch, "DRIP_FEED(000100.PRO/1/N2/3)") ==
             {:error, "BAD PROGRAM FILE 000100.PRO/1/N2/3"}

    assert parse(:monarch, "DRIP_FEED(000100.PRO") == {:error, :unknown}
  end

  test "property: every DRIP_FEED form is read back; anything else after DRIP_FEED is an error in words, never a crash" do
    forms =
      :proper.forall(
        {:proper_types.range(0, 999_999),
         :proper_types.oneof([:latest, :proper_types.range(1, 999_999)]),
         :proper_types.range(1, 9_999_999)},
        fn {p, v, k} ->
          file = String.pad_leading(Integer.to_string(p), 6, "0") <> ".PRO"
          version = if v == :latest, do: "", else: "/#{v}"
          line = if k == 1, do: "", else: "/N#{k}"

          parse(:monarch, "DRIP_FEED(#{file}#{version}#{line})") ==
            {:ok, {:drip_feed, file, v, k}}
        end
      )

    assert_property(forms, 300)

    other =
      :proper.forall(:proper_types.list(:proper_types.range(32, 126)), fn chars ->
        text = "DRIP_FEED" <> List.to_string(chars)

        case parse(:monarch, text) do
          {:ok, :drip_feed} -> true
          {:ok, {:drip_feed, file, _v, k}} -> file =~ ~r/^\d{6}\.PRO$/ and k >= 1
          {:error, :unknown} -> true
          {:error, words} -> words =~ ~r/^[A-Z0-9 .\/()_:,;-]+$/ or words =~ ~r/^BAD /
        end
      end)

    assert_property(other, 500)
  end

  test "gripper, vise, vacuum and hydraulic sets" do
    assert parse(:gripper, "CLOSE") == {:ok, :close}
    assert parse(:gripper, "ROTATE_270") == {:ok, {:rotate, 270}}
    assert parse(:gripper, "ROTATE_45") == {:error, :unknown}
    assert parse(:fixture, "DISABLE_TABLE") == {:ok, :disable_table}
    assert parse(:vacuum, "ON") == {:ok, :on}
    assert parse(:hydraulic, "CLAMP_PALLET") == {:ok, :clamp_pallet}
    assert parse(:hydraulic, "OPEN") == {:error, :unknown}
  end
end
