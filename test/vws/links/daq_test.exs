defmodule Vws.Links.DAQTest do
  use ExUnit.Case, async: true

  alias Vws.Links.DAQ
  alias Vws.Links.DAQ.{DeviceStatus, Readings}

  doctest Vws.Links.DAQ
  doctest Vws.Links.DAQ.Readings
  doctest Vws.Links.DAQ.DeviceStatus

  # Channel map of priv/plant.exs, written out: slot 1 channel => volts of a state.
  @closed 5.0
  @open 0.0
  @overload 9.9e37

  # A reading of every slot-1 channel (101..116) from a map of overrides, open switches elsewhere.
  defp volts(overrides) do
    for ch <- 101..116, do: Map.get(overrides, ch, @open)
  end

  defp readings(volt_overrides, ohms \\ 350.0) do
    DAQ.readings(DAQ.new(), [volts(volt_overrides), [ohms]])
  end

  # the shipped map with channel 116 back to spare
  @spare_116 %{daq1: %{116 => %{kind: :spare, signal: :spare}}}

  describe "the driver" do
    test "an answer with more or fewer readings than its channels is never read" do
      daq = DAQ.new()
      # (the HPIB never hands one over: SCPI checks the count of every answer line)
      assert_raise FunctionClauseError, fn -> DAQ.readings(daq, [tl(volts(%{})), [350.0]]) end

      assert_raise FunctionClauseError, fn ->
        DAQ.readings(daq, [volts(%{}) ++ [0.0], [350.0]])
      end

      assert_raise FunctionClauseError, fn -> DAQ.readings(daq, [volts(%{}), [350.0, 1.0]]) end
      r = DAQ.readings(daq, [volts(%{}), [350.0]])
      assert map_size(r.volts) == 16 and r.ohms == %{117 => 350.0}
    end

    test "reads slot 1 as one voltage scan and the gauge as one resistance reading" do
      assert DAQ.poll_commands(DAQ.new()) == [
               {:meas_volt_dc?, Enum.to_list(101..116)},
               {:meas_res?, [117]}
             ]
    end

    test "converts with the constants of the channel map" do
      # jaw pot: 0.5 V + 0.05 V/mm; finger pot: 0.2 V + 0.1 V/mm; gauge: 350 ohm + 0.01 ohm/N
      r = readings(%{103 => 4.25, 108 => 1.45, 104 => @closed, 113 => 2.6, 105 => 2.4}, 353.1)
      assert_in_delta r.values.vise_jaw_mm, 75.0, 1.0e-9
      assert_in_delta r.values.gripper_finger_mm, 12.5, 1.0e-9
      assert_in_delta r.values.vise_force_n, 310.0, 1.0e-6
      assert r.values.table_park == true
      # 2.5 V threshold
      assert r.values.vacuum_on == true
      assert r.values.tray1_in == false
      refute Map.has_key?(r.values, :spare)
      assert length(Readings.array_b(r)) == 16
      assert Readings.channel(r, :vise_force_n) == 117
    end

    test "an overload reading is an open circuit, never a number" do
      r = readings(%{103 => @overload, 101 => @overload}, @overload)
      assert r.values.vise_jaw_mm == :open_circuit
      assert r.values.vise_part_present == :open_circuit
      assert r.values.vise_force_n == :open_circuit
    end

    test "a switch can be wired to a spare channel; anything else is refused" do
      daq = DAQ.new(channel_map: @spare_116, switches: [changer1_released: 116])
      r = DAQ.readings(daq, [volts(%{116 => @closed}), [350.0]])
      assert r.values.changer1_released == true
      assert_raise ArgumentError, fn -> DAQ.new(switches: [changer1_released: 103]) end
    end

    @slot Enum.to_list(201..210)

    test "actuation: the whole slot read twice and nothing written; then opens before closes, the last word wins, the whole slot read back" do
      daq = DAQ.new()
      assert DAQ.slot(daq) == @slot
      q = {:rout_clos?, @slot}

      assert DAQ.actuation(daq, [{:gripper_open_solenoid, :close}, {202, :open}, {207, :close}]) ==
               {:ok, [q, q], {:before, @slot, [{201, true}, {202, false}, {207, true}]}}

      assert {:ok, _, {:before, _, [{207, false}]}} =
               DAQ.actuation(daq, [{207, :close}, {207, :open}])

      assert DAQ.actuation(daq, []) == {:ok, [], []}

      assert DAQ.actuation(daq, [{:vise_jaw_mm, :close}]) ==
               {:error, {:unknown_actuator, :vise_jaw_mm}}

      assert DAQ.actuation(daq, [{117, :close}]) == {:error, {:unknown_actuator, 117}}

      # the reads agree: the write, and the whole slot it must leave (205 closed before stays so)
      {:ok, _, before} = DAQ.actuation(daq, [{201, :close}, {202, :open}, {207, :close}])

      assert DAQ.confirm_relays(before, [states([202, 205]), states([202, 205])], "DAQ #1") ==
               {:next, [{:rout_open, [202]}, {:rout_clos, [201, 207]}, q],
                {:whole, Enum.map(@slot, &{&1, &1 in [201, 205, 207]})}}

      # reads alone confirm nothing
      assert DAQ.check_relays(before, [states([]), states([])]) == {:error, []}
    end

    # slot states as a list of booleans, the channels given closed
    defp states(closed), do: Enum.map(@slot, &(&1 in closed))

    # the write of 207 after the reads before it found `closed`
    defp write_207(closed) do
      {:ok, _, before} = DAQ.actuation(DAQ.new(), [{207, :close}])
      {:next, _, whole} = DAQ.confirm_relays(before, [states(closed), states(closed)], "DAQ #1")
      {before, whole}
    end

    test "the read-back is checked against the whole slot: the commanded relay and every other" do
      {_before, expected} = write_207([205])

      assert DAQ.check_relays(expected, [:ok, :ok, states([205, 207])]) == :ok
      # ROUT:CLOS (@207) arrived as (@206): 207 not closed, 206 closed — both found
      results = [:ok, states([205, 206])]
      assert DAQ.check_relays(expected, results) == {:error, [206, 207]}

      assert DAQ.confirm_relays(expected, results, "DAQ #1") ==
               {:error, "RELAY 206 NOT AS COMMANDED"}

      # set right: 206 opened, 207 closed, the slot read again and compared whole
      assert {:ok, [{:rout_open, [206]}, {:rout_clos, [207]}, {:rout_clos?, @slot}], ^expected} =
               DAQ.correction(expected, results)

      assert DAQ.check_relays(expected, [:ok, :ok, states([205, 207])]) == :ok
      assert DAQ.check_relays(expected, [:ok, :ok, states([207])]) == {:error, [205]}

      # no answer at all (the write may have been done): read again, never written blindly,
      # and held against the slot as read BEFORE the write — 206 closed by a damaged write is
      # found, never taken for intended
      assert DAQ.recheck(expected) == [{:rout_clos?, @slot}]
      assert DAQ.check_relays(expected, [states([205, 206])]) == {:error, [206, 207]}
      assert DAQ.check_relays(expected, [states([205, 207])]) == :ok

      # the write answered, the read-back missing: read again, whole
      assert DAQ.check_relays(expected, [:ok, :ok]) == {:error, []}

      assert {:ok, [{:rout_clos?, @slot}], ^expected} = DAQ.correction(expected, [:ok, :ok])
    end

    test "the two reads before a write disagree on a relay not commanded: read again, nothing written" do
      {before, _} = write_207([205])
      disagree = [states([205]), states([])]

      assert DAQ.confirm_relays(before, disagree, "DAQ #1") ==
               {:error, "DAQ #1 RELAYS NOT READ BACK"}

      assert DAQ.correction(before, disagree) ==
               {:ok, [{:rout_clos?, @slot}, {:rout_clos?, @slot}], before}

      # their answers lost: the same reads again (nothing was written)
      assert DAQ.recheck(before) == [{:rout_clos?, @slot}, {:rout_clos?, @slot}]
      # a disagreement on the commanded relay itself does not matter: it is written anyway
      assert {:next, _, _} =
               DAQ.confirm_relays(before, [states([205, 207]), states([205])], "DAQ #1")
    end
  end

  describe "device-status texts (PROTOCOLS.md §1)" do
    test "GRIPPER" do
      assert DeviceStatus.gripper(readings(%{107 => @closed, 108 => 8.2, 110 => @closed})) ==
               "GRIPPER IS OPEN AND INDEXER ROTATED 90 DEG"

      assert DeviceStatus.gripper(readings(%{108 => 1.45, 109 => @closed})) ==
               "FINGERS ARE 12.5 MM APART AND INDEXER ROTATED 0 DEG"

      # fingers on each other, with the pot's noise below zero
      assert DeviceStatus.gripper(readings(%{108 => 0.196, 112 => @closed})) ==
               "FINGERS ARE 0.0 MM APART AND INDEXER ROTATED 270 DEG"

      assert DeviceStatus.gripper(readings(%{108 => 1.45})) =~ "INDEXER BETWEEN POSITIONS"

      assert DeviceStatus.gripper(readings(%{108 => 1.45, 109 => @closed, 111 => @closed})) =~
               "INDEXER SWITCHES DISAGREE"

      assert DeviceStatus.gripper(readings(%{108 => @overload})) ==
               "NO DATA (GRIPPER SENSOR CH 108 OPEN CIRCUIT)"
    end

    test "TABLE, TRAYS, VACUUM" do
      assert DeviceStatus.table(readings(%{104 => @closed})) == "TABLE IN PARK POSITION"
      assert DeviceStatus.table(readings(%{})) == "TABLE NOT IN PARK POSITION"

      assert DeviceStatus.trays(readings(%{105 => @closed})) ==
               "TRAY #1 IN POSITION TRAY #2 NOT IN POSITION"

      assert DeviceStatus.trays(readings(%{106 => @closed})) ==
               "TRAY #1 NOT IN POSITION TRAY #2 IN POSITION"

      assert DeviceStatus.vacuum(readings(%{113 => @closed})) == "VACUUM IS ON"
      assert DeviceStatus.vacuum(readings(%{})) == "VACUUM IS OFF"
    end

    test "VISE: locked from the minimum clamping force, part from its switch" do
      locked = readings(%{101 => @closed, 103 => 3.0}, 358.0)

      assert DeviceStatus.vise(locked) ==
               "VISE JAWS ARE 50.0 MM APART AND VISE IS LOCKED PART IN VISE"

      assert DeviceStatus.vise(locked, min_force_n: 900) =~ "VISE IS UNLOCKED PART IN VISE"

      assert DeviceStatus.vise(readings(%{102 => @closed, 103 => 8.0})) ==
               "VISE JAWS ARE 150.0 MM APART AND VISE IS UNLOCKED PART NOT IN VISE"

      assert DeviceStatus.vise(readings(%{103 => 3.0}, @overload)) ==
               "NO DATA (VISE SENSOR CH 117 OPEN CIRCUIT)"
    end

    test "CHANGER_1 only from a wired switch" do
      unwired = DAQ.new(channel_map: @spare_116)
      no_switch = DAQ.readings(unwired, [volts(%{}), [350.0]])
      assert DeviceStatus.changer_1(no_switch) == "NO DATA (CHANGER_1 NOT WIRED TO DAQ #1)"
      daq = DAQ.new()

      assert DeviceStatus.changer_1(DAQ.readings(daq, [volts(%{116 => @closed}), [350.0]])) ==
               "CHANGER_1 FINGERS RELEASED"

      assert DeviceStatus.changer_1(DAQ.readings(daq, [volts(%{}), [350.0]])) ==
               "CHANGER_1 FINGERS DID NOT RELEASE"
    end

    test "every text fits a status reply (94 characters)" do
      r = readings(%{103 => 8.0, 108 => 8.2}, 371.0)

      for {_loc, text} <- DeviceStatus.texts(r) do
        assert byte_size(text) <= 94
      end

      assert Map.keys(DeviceStatus.texts(r)) |> Enum.sort() == [1, 2, 3, 4, 5, 7]
    end
  end

  test "new/1 refuses an unknown option or a bad value, naming it" do
    assert_raise Vws.Options.Error, ~r/unknown DAQ option :switch/, fn ->
      Vws.Links.DAQ.new(switch: [changer1_released: 116])
    end

    assert_raise Vws.Options.Error, ~r/DAQ option :daq/, fn -> Vws.Links.DAQ.new(daq: :daq3) end
  end
end
