# The simulated VAL II robot (Vws.Sim.VAL2): its arm, its named locations, the work volumes the
# plant is told about, and the programs EXECUTE can run. Read once when a simulator starts
# (Code.eval_file); a test or a deployment may pass its own file with `locations:`.
#
# World frame: origin at the robot's base on the floor, Z up, X towards the machine tool, mm.
# Locations are VAL II locations {x, y, z, o, a, t}: position in mm and the Euler angles O, A, T
# in degrees, the rotation being Rz(O)·Ry(A)·Rz(T); the tool points along its own Z axis, so
# {_, _, _, 0, 180, 0} points the gripper straight down. See Vws.Sim.VAL2.Kinematics.
%{
  # A Unimate-style polar arm (seed §4.1: hydraulic, encoder feedback): base rotation j1,
  # boom pitch j2, boom extension j3 (mm), three wrist axes j4-j6.
  arm: %{
    # height of the boom's pitch axis above the floor
    shoulder_height: 1000.0,
    # wrist centre to pitch axis with the boom retracted (j3 = 0)
    boom_retracted: 650.0,
    # wrist centre to the tool point (gripper fingers), along the tool Z axis
    tool_length: 250.0,
    # joint ranges: j1 and j2 in degrees, j3 in mm; outside them a location is out of reach
    base: {-150.0, 150.0},
    pitch: {-45.0, 35.0},
    boom_stroke: {0.0, 900.0},
    # at SPEED 100: the fastest each joint moves (deg/s, j3 mm/s) in joint-interpolated motion,
    # and the tool's speed (mm/s, deg/s) in straight-line motion
    joint_speed: [90.0, 60.0, 500.0, 180.0, 180.0, 180.0],
    linear_speed: 500.0,
    angular_speed: 90.0
  },

  # Monitor speed at power-up (SPEED n sets it; n is a percentage of the speeds above)
  speed: 50.0,

  # Where the arm is at power-up
  start: "SAFE",
  locations: %{
    # clear of every work volume, gripper down
    "SAFE" => {800.0, 0.0, 1200.0, 0.0, 180.0, 0.0},
    # the roller tables: four part locations per tray, 63.5 mm (2.5 in) apart along -Y,
    # gripper down at the part's grip height
    "TRAY1" => {650.0, -450.0, 700.0, 0.0, 180.0, 0.0},
    "TRAY2" => {650.0, 640.5, 700.0, 0.0, 180.0, 0.0},
    # the vise on the machine-tool table, gripper down between the jaws
    "VISE" => {1200.0, 0.0, 850.0, 0.0, 180.0, 0.0},
    # Reference frames for compound transformations, as in seed Table 1:
    # MV1:TRANS(x/y/z/90/-90/T) is gripper-down, x mm along the tray from a point 300 mm above
    # location 2 of tray #1 (so TRANS(63.5,0,0,90,-90,0) is 300 mm above its location 3).
    # MV2 does the same above tray #2 from its location 1, MV3 above the vise. In these frames
    # local X runs along the tray (world -Y), local Y up (world +Z), local Z world -X.
    "MV1" => {650.0, -513.5, 1000.0, 180.0, 90.0, 90.0},
    "MV2" => {650.0, 640.5, 1000.0, 180.0, 90.0, 90.0},
    "MV3" => {1200.0, 0.0, 1150.0, 180.0, 90.0, 90.0}
  },

  # Work volumes, {x range, y range, z range} of the tool point; the first that holds it names
  # where the robot is (the plant's volumes); anywhere else is :safe.
  volumes: [
    vise: {{1050.0, 1350.0}, {-150.0, 150.0}, {750.0, 1200.0}},
    table: {{950.0, 1500.0}, {-400.0, 400.0}, {600.0, 1300.0}},
    tray1: {{450.0, 850.0}, {-750.0, -350.0}, {600.0, 1100.0}},
    tray2: {{450.0, 850.0}, {350.0, 750.0}, {600.0, 1100.0}}
  ],

  # Programs EXECUTE runs (the seed's process-control programs for real-time path control):
  # motion instructions in VAL II syntax, one after the other.
  programs: %{
    "DEBURR" => [
      "MOVE MV3:TRANS(0,0,0,90,-90,0)",
      "MOVES MV3:TRANS(0,-250,0,90,-90,0)",
      "MOVES MV3:TRANS(20,-250,0,90,-90,0)",
      "DEPARTS 250",
      "MOVE SAFE"
    ],
    "PARK" => ["MOVE SAFE"]
  }
}
