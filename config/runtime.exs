import Config

# Deployment values come from the environment, read once at boot (a release, or `mix run`).
# With VWS_WC set, the application starts one workstation itself; in dev and test nothing
# starts by itself (mix vws.serve / mix vws.demo / the tests start what they need).
if wc = System.get_env("VWS_WC") do
  config :vws, :workstation,
    id: System.get_env("VWS_ID", "VWS"),
    wc: wc,
    journal: System.get_env("VWS_JOURNAL_DIR")
end
