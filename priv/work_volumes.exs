# The interlocked work volumes of the robot's named locations, as the CEC's ROBOT knows them
# (seed §2.3.8, §4.4 Fig. 13: before the robot moves from SAFE into a work volume WVN the CEC
# checks the device lock-out of that volume). Read by Vws.Partitions.Robot (option
# `:work_volumes` overrides it); edit, restart the workstation, done.
#
# Volumes: :table (the machine-tool table: the vise and the pallet sit on it), :tray1 and :tray2
# (the roller tables of the material-handling system), :safe (clear of every interlocked volume).
# A compound location `NAME:TRANS(...)` lies in the volume of NAME (the frames are defined so);
# DO DEPART/DEPARTS stays in the volume the arm is in; DO APPRO/APPROS enters the volume of its
# location.
#
# A location or a program that is not listed here is refused before it reaches the robot:
# the CEC cannot apply an interlock it does not know (ERROR INTERLOCK NO WORK VOLUME FOR <name>).
# Set `default:` to a volume to give every unlisted location that volume instead.
#
# test/vws/cec/interlock/work_volumes_test.exs checks that every location of the simulated robot
# (priv/sims/robot_locations.exs) is listed here with the volume its geometry puts it in.
%{
  locations: %{
    "SAFE" => :safe,
    "TRAY1" => :tray1,
    "TRAY2" => :tray2,
    "VISE" => :table,
    # the reference frames of seed Table 1: above tray #1, above tray #2, above the vise
    "MV1" => :tray1,
    "MV2" => :tray2,
    "MV3" => :table
  },

  # Programs EXECUTE runs: the volumes the program enters (leases taken before it starts) and
  # where the arm is when it completes.
  programs: %{
    "DEBURR" => %{enters: [:table], ends: :safe},
    "PARK" => %{enters: [], ends: :safe}
  },

  # the volume of a location not listed above; nil: refuse it
  default: nil
}
