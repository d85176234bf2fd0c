import Config

# `mix vws.serve` and `mix vws.demo` log at info, as a release does (start-up, links coming and
# going, each condition once); VWS_LOG_LEVEL=debug (config/runtime.exs) for a developer's console.
config :logger, level: :info
