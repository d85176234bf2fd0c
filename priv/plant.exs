# VWS plant: the channel map of the two data-acquisition units, the conversion constants
# between physical quantities and what the DAQs read, and how fast the simulated plant moves.
#
# Read by `Vws.Links.DAQ.ChannelMap.load/1`: by the CEC's drivers (to find a channel by name and turn
# a reading back into millimetres or newtons) and by the plant simulator, which is wired by the
# product's map. It is one Elixir map, evaluated with `Code.eval_file/1`; edit a number, restart, done.
#
# Channel numbers are the DAQ's own: slot digit + two-digit channel (slot 1 = 101..120,
# slot 2 = 201..220), as they appear in SCPI channel lists, e.g. `MEAS:VOLT:DC? (@101:116)`.
#
# Kinds of channel:
#   :switch   a microswitch; the DAQ reads the voltage across the contacts (see `switch:` below)
#   :pot      a potentiometer; volts = volts_at_zero + volts_per_unit * value (mm or degrees)
#   :gauge    a strain gauge read as resistance; ohms = ohms_at_zero + ohms_per_newton * newtons,
#             so newtons = (ohms - ohms_at_zero) / ohms_per_newton
#   :spare    wired to nothing; reads open_volts plus noise
#   :actuator a relay of the actuator card; closing it (`ROUT:CLOS`) energises the device named
#
# Any channel may carry `noise:` to override the default noise of its kind (a half-width: the
# noise is uniform in -noise..+noise, so a reading never strays further than that).
%{
  # DAQ #1 — on the CEC's HPIB (seed §1.3, §2.3.6).
  daq1: %{
    # Slot 1: the sensors, the seed's 16-element array B, read with MEAS:VOLT:DC? (@101:116).
    # closed when a part sits on the vise's seat, whatever the jaws do
    101 => %{kind: :switch, signal: :vise_part_present},
    # closed when the vise jaws are fully open (the OPEN end stop)
    102 => %{kind: :switch, signal: :vise_fully_open},
    # vise jaw opening: 0 mm = 0.5 V, 150 mm (fully open) = 8.0 V
    103 => %{kind: :pot, signal: :vise_jaw_mm, volts_at_zero: 0.5, volts_per_unit: 0.05},
    # closed when the machine table is at its park position
    104 => %{kind: :switch, signal: :table_park},
    # closed when tray #1 is in position on its roller table
    105 => %{kind: :switch, signal: :tray1_in},
    # closed when tray #2 is in position on its roller table
    106 => %{kind: :switch, signal: :tray2_in},
    # closed when the gripper fingers are fully open
    107 => %{kind: :switch, signal: :gripper_fully_open},
    # gripper finger opening: 0 mm (fingers on each other) = 0.2 V, 80 mm = 8.2 V
    108 => %{kind: :pot, signal: :gripper_finger_mm, volts_at_zero: 0.2, volts_per_unit: 0.1},
    # closed when the rotary indexer stands at 0 degrees
    109 => %{kind: :switch, signal: :indexer_0},
    # ... at 90 degrees
    110 => %{kind: :switch, signal: :indexer_90},
    # ... at 180 degrees
    111 => %{kind: :switch, signal: :indexer_180},
    # ... at 270 degrees
    112 => %{kind: :switch, signal: :indexer_270},
    # vacuum pressure switch: closed once the chip-removal vacuum has drawn its pressure
    113 => %{kind: :switch, signal: :vacuum_on},
    # closed when the lock pin of tray #1 is engaged
    114 => %{kind: :switch, signal: :tray1_locked},
    # closed when the lock pin of tray #2 is engaged
    115 => %{kind: :switch, signal: :tray2_locked},
    # closed when the fingers of tool changer 1 have released (the CHANGER_1 status)
    116 => %{kind: :switch, signal: :changer1_released},
    # vise clamping force, read with MEAS:RES? (@117): 350 ohm unloaded, 370 ohm at 2000 N
    117 => %{kind: :gauge, signal: :vise_force_n, ohms_at_zero: 350.0, ohms_per_newton: 0.01},

    # Slot 2: the actuators, driven with ROUT:CLOS / ROUT:OPEN (@2nn).
    # gripper OPEN solenoid (pneumatic); with neither solenoid on the fingers hold
    201 => %{kind: :actuator, signal: :gripper_open_solenoid},
    # gripper CLOSE solenoid
    202 => %{kind: :actuator, signal: :gripper_close_solenoid},
    # indexer position select, low bit: position = (bit1 * 2 + bit0) * 90 degrees
    203 => %{kind: :actuator, signal: :indexer_bit0},
    # indexer position select, high bit
    204 => %{kind: :actuator, signal: :indexer_bit1},
    # vise OPEN valve; with neither valve on the vise holds its jaws and its force
    205 => %{kind: :actuator, signal: :vise_open_valve},
    # vise CLOSE valve
    206 => %{kind: :actuator, signal: :vise_close_valve},
    # vacuum motor contactor
    207 => %{kind: :actuator, signal: :vacuum_motor},
    # tray #1 lock: closed = the material-handling system cannot move tray #1
    208 => %{kind: :actuator, signal: :tray1_lock},
    # tray #2 lock
    209 => %{kind: :actuator, signal: :tray2_lock},
    # cycle-start relay wired to the machine tool's cycle-start input
    210 => %{kind: :actuator, signal: :cycle_start_relay}
  },

  # DAQ #2 — on the hydraulic controller's HPIB (seed §5): the pallet.
  daq2: %{
    # closed when the pallet is registered against its X stops
    101 => %{kind: :switch, signal: :pallet_x},
    # closed when the pallet is registered against its Y stops
    102 => %{kind: :switch, signal: :pallet_y},
    # swing clamp 1 force, MEAS:RES?: 350 ohm unloaded, 360 ohm at 5000 N
    103 => %{kind: :gauge, signal: :clamp1_force_n, ohms_at_zero: 350.0, ohms_per_newton: 0.002},
    # swing clamp 2 force
    104 => %{kind: :gauge, signal: :clamp2_force_n, ohms_at_zero: 350.0, ohms_per_newton: 0.002},
    # X positioning ram valve (spring return: open relay = ram retracts)
    201 => %{kind: :actuator, signal: :ram_x_valve},
    # Y positioning ram valve
    202 => %{kind: :actuator, signal: :ram_y_valve},
    # swing clamp 1 valve: closed = swing in and clamp; open = release and swing out
    203 => %{kind: :actuator, signal: :swing_clamp1_valve},
    # swing clamp 2 valve
    204 => %{kind: :actuator, signal: :swing_clamp2_valve}
  },

  # Microswitches: the DAQ sees the supply across the channel when the contacts are closed.
  switch: %{
    # reading of a closed (actuated) switch
    closed_volts: 5.0,
    # reading of an open switch, a broken switch or a cut wire
    open_volts: 0.0,
    # the CEC takes a switch as closed above this
    threshold_volts: 2.5,
    # default noise half-width, volts
    noise: 0.02
  },

  # Default noise half-widths of the other kinds.
  noise: %{pot_volts: 0.005, gauge_ohms: 0.05, spare_volts: 0.01},

  # What a DMM returns for an overload or an open input (HP/Agilent convention).
  overload: 9.9e37,

  # Geometry and motion. Times are simulated seconds for a full stroke; a shorter move takes
  # proportionally less. The plant's time_scale multiplies all of them.
  motion: %{
    # vise jaw opening when fully open
    vise_max_mm: 150.0,
    # fully open to fully closed
    vise_stroke_s: 1.5,
    # force the vise builds on a part
    vise_clamp_n: 2000.0,
    # zero to full clamp force once the jaws touch the part
    vise_force_rise_s: 0.3,
    # finger opening when fully open
    gripper_max_mm: 80.0,
    # fully open to fully closed
    gripper_stroke_s: 0.5,
    # rotary indexer, seconds per 90 degrees
    indexer_s_per_90: 1.0,
    # vacuum on until the pressure switch closes (and off until it opens)
    vacuum_s: 0.5,
    # roller-table travel of a tray between out and in position
    tray_travel_mm: 600.0,
    # a full tray move by the material-handling system
    tray_s: 6.0,
    # how far the machine table leaves park during a cycle
    table_travel_mm: 300.0,
    # park to cutting position and back, each way
    table_s: 2.0,
    # pallet positioning ram stroke; the pallet is at its stops at full stroke
    ram_stroke_mm: 25.0,
    # full ram stroke
    ram_s: 1.0,
    # swing clamp arm travel from released to on the pallet
    swing_deg: 90.0,
    # full swing
    swing_s: 1.0,
    # force each swing clamp builds on the pallet
    pallet_clamp_n: 5000.0,
    # zero to full pallet clamp force
    pallet_force_rise_s: 0.5,
    # an indexer position switch is closed within this many degrees of its position
    indexer_tolerance_deg: 1.0
  },

  # Parts: the width a part presents to the vise jaws and to the gripper fingers.
  part_width_mm: 50.0,

  # Robot work volumes that lie on the machine table (the vise and the pallet sit on it).
  table_volumes: [:table, :vise, :pallet]
}
