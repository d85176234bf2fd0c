import Config

config :logger, :console, metadata: [:workstation, :partition, :command]

import_config "#{config_env()}.exs"
