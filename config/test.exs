import Config

config :logger, level: :warning

# VWS_STATUS's load shedding is node-wide: the suite's async tests would slow each other's polls
# down. Tests that shed give VWS_STATUS a pool of their own (`shedding:`).
config :vws, vws_status_shedding: false
