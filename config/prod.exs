import Config

# A release logs at info (start-up, links coming and going, each condition once — Vws.LogLimit);
# debug is for a developer's console. VWS_LOG_LEVEL changes it at boot (config/runtime.exs).
config :logger, level: :info
