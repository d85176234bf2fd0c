defmodule Vws.Ops.MTConnect.ModelTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Ops.MTConnect.Model

  doctest Vws.Ops.MTConnect.Model

  describe "status texts (PROTOCOLS.md §1) to MTConnect values" do
    test "VMC" do
      assert Model.vmc_execution("ACTIVE") == "ACTIVE"
      assert Model.vmc_execution("IDLE") == "READY"
      assert Model.vmc_execution("NO DATA (NO LINK TO GE-2000)") == "UNAVAILABLE"
      assert Model.vmc_execution(nil) == "UNAVAILABLE"
      refute Model.vmc_available?("NO DATA (NO LINK TO GE-2000)")
      assert Model.vmc_available?("IDLE")
    end

    test "robot" do
      assert Model.robot_position("350.5/-12/400/90/0/0/1/2/3/4/5/6") == "350.5 -12 400"
      assert Model.robot_position("1,2,3") == "1 2 3"
      assert Model.robot_position("NO DATA (NO LINK TO VAL II)") == nil
      assert Model.robot_position("1/2") == nil
      assert Model.robot_execution(:executing) == "ACTIVE"
      assert Model.robot_execution(:done) == "READY"
      assert Model.robot_execution({:error, "COLLISION"}) == "STOPPED"
    end

    test "gripper, vise, trays, pallet" do
      assert Model.gripper_state("GRIPPER IS OPEN AND INDEXER ROTATED 90 DEG") == "OPEN"

      assert Model.gripper_state("FINGERS ARE 12.5 MM APART AND INDEXER ROTATED 0 DEG") ==
               "CLOSED"

      assert Model.gripper_state("NO DATA (NO LINK TO DAQ #1)") == "UNAVAILABLE"

      assert Model.vise_state("VISE IS UNLOCKED PART NOT IN VISE") == "OPEN"
      assert Model.vise_part("VISE IS UNLOCKED PART NOT IN VISE") == "NOT_PRESENT"
      locked = "VISE JAWS ARE 75 MM APART AND VISE IS LOCKED PART IN VISE"
      assert Model.vise_state(locked) == "CLOSED"
      assert Model.vise_part(locked) == "PRESENT"
      assert Model.vise_state("NO DATA (NO LINK TO DAQ #1)") == "UNAVAILABLE"

      trays = "TRAY #1 IN POSITION TRAY #2 NOT IN POSITION"
      assert Model.tray_state(trays, 1) == "LOCKED"
      assert Model.tray_state(trays, 2) == "UNLOCKED"
      assert Model.tray_state("NO DATA (NO LINK TO DAQ #1)", 1) == "UNAVAILABLE"
      assert Model.tray_state("TRAY #12 IN POSITION TRAY #1 NOT IN POSITION", 1) == "UNLOCKED"

      assert Model.pallet_state("PALLET CLAMPED") == "LOCKED"
      assert Model.pallet_state("PALLET NOT CLAMPED") == "UNLOCKED"
      assert Model.pallet_state("NO DATA (NO LINK TO HYDRAULIC CONTROLLER)") == "UNAVAILABLE"
    end

    test "the program is the last PROGRAM_SELECT, kept across other commands" do
      assert Model.program("PROGRAM_SELECT(000123)", nil) == "000123"
      assert Model.program("CYCLE_START", "000123") == "000123"
      assert Model.program(nil, nil) == nil
    end
  end

  describe "the device" do
    test "ids are XML names, unique per workstation, names are the workstation ids" do
      a = Model.device("VWS 1")
      b = Model.device("VWS_1")
      assert a.name == "VWS 1"
      assert a.id =~ ~r/^[A-Za-z_][A-Za-z0-9_.\-]*$/
      assert a.id != b.id
      assert Model.device(:vws).name == "vws"

      ids = Enum.map(Model.items(a), & &1.id)
      assert ids == Enum.uniq(ids)
    end

    test "models the VMC, robot, gripper, vise, trays and pallet" do
      d = Model.device("VWS")
      types = for i <- Model.items(d), do: {i.component_name, i.type}

      for expected <- [
            {"VWS", "AVAILABILITY"},
            {"vmc", "AVAILABILITY"},
            {"vmc", "CONTROLLER_MODE"},
            {"path", "EXECUTION"},
            {"path", "PROGRAM"},
            {"path", "PATH_POSITION"},
            {"gripper", "CHUCK_STATE"},
            {"vise", "CHUCK_STATE"},
            {"vise", "PART_DETECT"},
            {"tray1", "LOCK_STATE"},
            {"tray2", "LOCK_STATE"},
            {"pallet", "LOCK_STATE"}
          ] do
        assert expected in types
      end
    end

    test "without facts every item is UNAVAILABLE; with them the device is AVAILABLE" do
      d = Model.device("VWS")

      assert d |> Model.observe(nil) |> Map.values() |> Enum.uniq() |> Enum.sort() ==
               [{:condition, "Unavailable", nil, ""}, "UNAVAILABLE"]

      facts = %{
        devices: %{"MONARCH" => "IDLE", "PALLET" => "PALLET CLAMPED"},
        commands: %{robot: {7, :executing}},
        program: "000042"
      }

      v = Model.observe(d, facts)
      assert v["ws_VWS_avail"] == "AVAILABLE"
      assert v["ws_VWS_vmc_path_exec"] == "READY"
      assert v["ws_VWS_vmc_mode"] == "AUTOMATIC"
      assert v["ws_VWS_vmc_path_program"] == "000042"
      assert v["ws_VWS_robot_avail"] == "AVAILABLE"
      assert v["ws_VWS_robot_path_exec"] == "ACTIVE"
      assert v["ws_VWS_pallet_state"] == "LOCKED"
      assert v["ws_VWS_vise_state"] == "UNAVAILABLE"
    end
  end

  test "property: a tray's state is the first \"TRAY #n [NOT ]IN POSITION\" of that tray in the text" do
    part =
      :proper_types.oneof([
        :proper_types.elements(["TRAY ", "#", "1", "2", "12", " ", "NOT ", "IN POSITION", "X"]),
        :proper_types.elements([
          "TRAY #1 IN POSITION",
          "TRAY #2 NOT IN POSITION",
          "TRAY 1 NOT IN POSITION"
        ])
      ])

    property =
      :proper.forall({:proper_types.list(part), :proper_types.elements([1, 2])}, fn {parts, n} ->
        text = Enum.join(parts)

        # the rule as a regex of its own for the tray
        expected =
          case Regex.run(Regex.compile!("TRAY #?#{n} (NOT )?IN POSITION"), text) do
            [_, "NOT "] -> "UNLOCKED"
            [_] -> "LOCKED"
            _ -> "UNAVAILABLE"
          end

        Model.tray_state(text, n) == expected
      end)

    assert_property(property, 500)
  end

  describe "a change's few items worked out alone (Model.changed_values/3)" do
    alias Vws.Ops.MTConnect.Agent

    # DAQ #1's readings from random volts and a random gauge
    defp readings do
      :proper_types.bind(
        {:proper_types.vector(16, :proper_types.float(0.0, 10.0)),
         :proper_types.float(100.0, 600.0)},
        fn {volts, ohms} -> Vws.Links.DAQ.readings(Vws.Links.DAQ.new(), [volts, [ohms]]) end,
        false
      )
    end

    defp text do
      :proper_types.elements([
        nil,
        "GRIPPER IS OPEN AND INDEXER ROTATED 90 DEG",
        "FINGERS ARE 12.5 MM APART AND INDEXER ROTATED 0 DEG",
        "VISE JAWS ARE 75 MM APART AND VISE IS LOCKED PART IN VISE",
        "VISE IS FULLY OPEN PART NOT IN VISE",
        "TRAY #1 IN POSITION TRAY #2 NOT IN POSITION",
        "TRAY #1 NOT IN POSITION TRAY #2 IN POSITION",
        "PALLET CLAMPED",
        "IDLE",
        "ACTIVE",
        {:no_data, "NO LINK TO DAQ #1"},
        "NO DATA (DAQ #1 NOT ANSWERING)"
      ])
    end

    @names ~w(GRIPPER TABLE VISE TRAYS VACUUM MONARCH WHERE_ROBOT PALLET SENSORS)

    defp facts do
      :proper_types.bind(
        {:proper_types.list(
           :proper_types.oneof([
             {:proper_types.elements(@names -- ["SENSORS"]), text()},
             {:proper_types.exactly("SENSORS"), :proper_types.oneof([readings(), text()])}
           ])
         ), :proper_types.elements([%{}, %{robot: {7, :executing}, gripper: {3, :done}}])},
        fn {devices, commands} -> %{devices: Map.new(devices), commands: commands} end,
        false
      )
    end

    defp change do
      :proper_types.oneof([
        {:proper_types.elements(@names -- ["SENSORS"]), text()},
        {:proper_types.exactly("SENSORS"), :proper_types.oneof([readings(), text()])}
      ])
    end

    test "property: the items it gives are the whole device's observed again, and no other item changed" do
      device = Model.device("VWS")

      property =
        :proper.forall({facts(), change()}, fn {before, {name, value}} ->
          loc = Vws.CEC.Mailbox.device_location(name)
          after_change = Agent.apply_change(before, {:device, loc, value})
          whole = Model.observe(device, after_change)

          case Model.changed_values(device, {:device, name, value}, before) do
            {:only, values} ->
              Map.merge(Model.observe(device, before), values) == whole

            :all ->
              true
          end
        end)

      assert_property(property, 1_000)
    end

    test "a poll's SENSORS and VISE are worked out alone; a first reading, MONARCH or PALLET is not" do
      device = Model.device("VWS")
      r = Vws.Links.DAQ.readings(Vws.Links.DAQ.new(), [List.duplicate(1.0, 16), [300.0]])
      with_readings = %{devices: %{"SENSORS" => r}}

      assert {:only, %{"ws_VWS_vise_force" => _} = v} =
               Model.changed_values(device, {:device, "SENSORS", r}, with_readings)

      assert map_size(v) == 3
      assert {:only, _} = Model.changed_values(device, {:device, "VISE", "VISE IS LOCKED"}, %{})
      assert Model.changed_values(device, {:device, "SENSORS", r}, %{}) == :all
      assert Model.changed_values(device, {:device, "MONARCH", "IDLE"}, with_readings) == :all
      assert Model.changed_values(device, {:device, "PALLET", "PALLET CLAMPED"}, %{}) == :all
    end
  end
end
