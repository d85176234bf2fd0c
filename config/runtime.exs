import Config

# Deployment values come from the environment, read once at boot (a release, or `mix run`).
# With VWS_WC set, the application starts one workstation itself; in dev and test nothing
# starts by itself (mix vws.serve / mix vws.demo / the tests start what they need).
#
#   VWS_ID            the workstation id (default VWS); also its MTConnect device name
#   VWS_WC            the WC endpoint: tty:/dev/ttyS0?baud=9600 or tcp://0.0.0.0:7070
#   VWS_WC_ALLOW      who may connect to a TCP WC port: 10.0.0.5,10.0.0.0/24 (default loopback
#                     only; required when VWS_WC listens on another address)
#   VWS_BCC           sum (default) or xor: the WC link's block check
#   VWS_DATA_DIR      the data directory (default $XDG_STATE_HOME/vws, else ~/.local/state/vws);
#                     the journal is in journal/<VWS_ID> of it (Vws.Ops.DataDir)
#   VWS_JOURNAL_DIR   the command journal's directory instead; "off": no journal
#   VWS_LIBRARY_DIR   the program library's directory instead of library/<VWS_ID>; "off": none
#   VWS_ROBOT         the VAL II's supervisory port (tty:/dev/ttyS1?baud=9600 or tcp://…)
#   VWS_GE2000        the GE-2000's DNC port (tty:/dev/ttyS2?baud=4800 or tcp://…)
#   VWS_DAQ1, VWS_DAQ2, VWS_HYDRAULIC
#                     the HPIB instruments' endpoints (tcp://gpib-gateway:1234 …)
#   VWS_STATUS_WAKE_EARLY_US  µs VWS_STATUS waits on the CPU before each DAQ #1 poll (2000; 0: none)
#   VWS_HTTP_PORT     the dashboard and MTConnect agent (default 4000 in a release; "off": none)
#   VWS_HTTP_BIND     the address they listen on (default 127.0.0.1)
#   VWS_HTTP_TOKEN    enables the dashboard's control actions for requests carrying it
#   VWS_HTTP_TOKEN_FILE  the control token from this file instead (mode 0600; Vws.Ops.Web.Tokens)
#   VWS_LOG_DIR       the log also goes to DIR/vws-<VWS_ID>.log, rotated at 10 MB, 10 old files kept
#                     (Vws.Ops.LogFile); a release's default is its own log/ directory; "off": none
#   VWS_LOG_LEVEL     debug, info (a release's default), notice, warning or error
#   VWS_HTTP_READ_TOKEN  every read of the dashboard and MTConnect agent needs it (Basic password)
#   VWS_HTTP_READ_TOKEN_FILE  the read token from this file instead

# A value that cannot be used stops the node at once with one line naming the variable, status 1
# — not a stack trace and an erl_crash.dump in the working directory (a raise here is both).
fail = fn line ->
  IO.puts(:stderr, "ERROR: " <> line)
  System.halt(1)
end

integer = fn name, text ->
  case Integer.parse(text) do
    {n, ""} when n >= 0 -> n
    _ -> fail.("#{name} must be a whole number, not #{text}")
  end
end

env = fn name ->
  case System.get_env(name) do
    nil -> nil
    value -> if String.trim(value) == "", do: nil, else: String.trim(value)
  end
end

if wc = env.("VWS_WC") do
  devices =
    for {device, var} <- [
          robot: "VWS_ROBOT",
          ge2000: "VWS_GE2000",
          daq1: "VWS_DAQ1",
          daq2: "VWS_DAQ2",
          hydraulic: "VWS_HYDRAULIC"
        ],
        endpoint = env.(var),
        do: {device, endpoint}

  # VWS_STATUS polls DAQ #1 on time to within microseconds by waiting the last 2 ms before each
  # poll on the CPU (Vws.Partitions.VwsStatus, :wake_early_us); VWS_STATUS_WAKE_EARLY_US=0 sleeps
  wake_early_us = integer.("VWS_STATUS_WAKE_EARLY_US", env.("VWS_STATUS_WAKE_EARLY_US") || "2000")

  devices =
    Enum.map(devices, fn
      {:daq1, endpoint} -> {:daq1, endpoint: endpoint, vws_status: [wake_early_us: wake_early_us]}
      other -> other
    end)

  bcc =
    case env.("VWS_BCC") do
      nil -> :sum
      "sum" -> :sum
      "xor" -> :xor
      other -> fail.("VWS_BCC must be sum or xor, not #{other}")
    end

  config :vws, :workstation,
    id: env.("VWS_ID") || "VWS",
    wc: wc,
    # on by default (issue 15): a restart forgets nothing acknowledged
    journal: Vws.Ops.DataDir.journal_dir(env.("VWS_ID") || "VWS", :default),
    # the program library (issue 18), library/<VWS_ID> of the data directory (VWS_LIBRARY_DIR)
    library: Vws.Ops.DataDir.library_dir(env.("VWS_ID") || "VWS", :default),
    sun_comm: [bcc: bcc, allow: env.("VWS_WC_ALLOW")],
    devices: devices
end

http_port =
  case {env.("VWS_HTTP_PORT"), config_env()} do
    {"off", _} -> nil
    {nil, :prod} -> 4000
    {nil, _} -> nil
    {_, :test} -> nil
    {port, _} -> integer.("VWS_HTTP_PORT", port)
  end

if http_port do
  # the tokens from their files or the environment, never from a command line (Vws.Ops.Web.Tokens)
  token = fn
    {:ok, token} -> token
    {:error, message} -> fail.(message)
  end

  config :vws, :http,
    port: http_port,
    bind: env.("VWS_HTTP_BIND") || "127.0.0.1",
    token: token.(Vws.Ops.Web.Tokens.control()),
    read_token: token.(Vws.Ops.Web.Tokens.read())
end

# The log: to rotating files as well as the console (Vws.Ops.LogFile), at the level asked.
if config_env() != :test do
  log_dir =
    case {env.("VWS_LOG_DIR"), System.get_env("RELEASE_ROOT")} do
      {"off", _} -> nil
      {nil, nil} -> nil
      {nil, release_root} -> Path.join(release_root, "log")
      {dir, _} -> Path.expand(dir)
    end

  if log_dir, do: config(:vws, :log_file, dir: log_dir)

  case env.("VWS_LOG_LEVEL") do
    nil ->
      :ok

    level when level in ~w(debug info notice warning error) ->
      config :logger, level: String.to_atom(level)

    other ->
      fail.("VWS_LOG_LEVEL must be debug, info, notice, warning or error, not #{other}")
  end
end
