defmodule Vws.Ops.MTConnect.Model do
  @moduledoc """
  How a workstation is shown as an MTConnect device, and how its mailboxes read as MTConnect
  observations. Pure: no processes, no I/O.

  Each workstation is one `Device` (its name is the workstation id); the tree, with every data
  item, is in `docs/mtconnect.md`:

  ```
  Device <ws>                     Availability (the workstation runs)
  ├── Controller vmc              Availability, ControllerMode, Message, command, SYSTEM condition
  │   └── Path vmc_path           Execution, Program, PartCount, dnc_transfer
  ├── Controller robot            Availability, ControllerMode, Message (its command), SYSTEM
  │   ├── Path robot_path         Execution, Program, PathPosition (x y z, mm)
  │   └── Axes arm                Linear X/Y/Z Position (mm), Rotary J1–J6 Angle (°)
  ├── EndEffector gripper         Availability, ChuckState, finger_gap (mm), Message, command, SYSTEM
  ├── Chuck vise                  Availability, ChuckState, PartDetect, jaw_width (mm),
  │                               clamp_force (N), Message, command, SYSTEM
  ├── Lock tray1, Lock tray2      LockState (tray locked in position)
  ├── Clamp pallet                Availability, LockState, clamp1/2_force (N), Message, command, SYSTEM
  └── Adapter wc/val/dnc/daq1/hydraulic_link   ConnectionStatus
  ```

  ## From mailbox texts to MTConnect values

  | item | rule |
  |------|------|
  | VMC availability | `AVAILABLE` when MONARCH reads `ACTIVE…`/`IDLE…`, else `UNAVAILABLE` |
  | VMC execution | MONARCH `ACTIVE` → `ACTIVE`, `IDLE` → `READY` |
  | VMC controller mode | `AUTOMATIC` (under DNC) while the VMC is available |
  | VMC program | the last `PROGRAM_SELECT(n)` commanded, else `UNAVAILABLE` |
  | robot availability | its link is up, WHERE_ROBOT holds a position, or a robot command is executing or done |
  | robot message | its latest command, number and status (`0012 DO MOVE TRAY1 DONE`) |
  | samples | DAQ #1's poll (jaw width, finger gap, vise force), the hydraulic controller's answer (clamp forces), WHERE_ROBOT (arm) |
  | robot execution | robot command `EXECUTING` → `ACTIVE`, `DONE`/none → `READY`, `ERROR` → `STOPPED` |
  | robot position | the first three numbers of WHERE_ROBOT (`x/y/z/…`) |
  | gripper | `…IS OPEN…` → `OPEN`; `…CLOSED…` or `FINGERS ARE…` → `CLOSED` |
  | vise | `…UNLOCKED…` → `OPEN`, `…LOCKED…` → `CLOSED`; `PART IN VISE` → `PRESENT`, `PART NOT IN VISE` → `NOT_PRESENT` |
  | trays | `TRAY #n IN POSITION` → `LOCKED`, `TRAY #n NOT IN POSITION` → `UNLOCKED` |
  | pallet | `PALLET CLAMPED` → `LOCKED`, `PALLET NOT CLAMPED` → `UNLOCKED` |

  Anything else, and every `NO DATA …`, is `UNAVAILABLE`: the agent never guesses.

      iex> Vws.Ops.MTConnect.Model.vise_state("VISE JAWS ARE 0 MM APART AND VISE IS LOCKED PART IN VISE")
      "CLOSED"
      iex> Vws.Ops.MTConnect.Model.tray_state("TRAY #1 IN POSITION TRAY #2 NOT IN POSITION", 2)
      "UNLOCKED"
  """

  @unavailable "UNAVAILABLE"

  @typedoc "One data item of the device model."
  @type item :: %{
          id: String.t(),
          type: String.t(),
          category: :event | :sample | :condition,
          element: String.t(),
          units: String.t() | nil,
          name: String.t() | nil,
          sub_type: String.t() | nil,
          deadband: number | nil,
          component: String.t(),
          component_id: String.t(),
          component_name: String.t(),
          device: String.t(),
          device_uuid: String.t()
        }

  @typedoc "A component of the device model (nested)."
  @type component :: %{
          type: String.t(),
          id: String.t(),
          name: String.t(),
          items: [item],
          components: [component]
        }

  @typedoc "A device: the workstation as MTConnect sees it."
  @type device :: %{
          id: String.t(),
          name: String.t(),
          uuid: String.t(),
          items: [item],
          components: [component]
        }

  @typedoc """
  What the agent knows of a workstation, kept current from its mailboxes' change notices
  (`Vws.CEC.Mailbox`, "Change notices"): the device-status texts by name, each partition's command
  `{number, status}` and latest command text, the readings (`:pallet` — the hydraulic
  controller's answer, `:monarch` — the GE-2000's status report), the device links' and WC
  link's connection states, the VMC's program and the parts counted.
  """
  @type facts :: %{
          optional(:devices) => %{String.t() => term},
          optional(:commands) => %{atom => {non_neg_integer | nil, term}},
          optional(:cmd_in) => %{atom => String.t() | nil},
          optional(:readings) => %{atom => term},
          optional(:links) => %{atom => String.t()},
          optional(:program) => String.t() | nil,
          optional(:part_count) => non_neg_integer,
          optional(:transfer) => String.t() | nil
        }

  @typedoc "A value: text (events; samples as text), a number (samples), or a condition."
  @type value :: String.t() | number | {:condition, String.t(), String.t() | nil, String.t()}

  # Item specs: {key, type, element, category, units, opts}; opts: :sub_type, :deadband (the
  # least change recorded: MTConnect's MINIMUM_DELTA filter), :name.
  @avail {"avail", "AVAILABILITY", "Availability", :event, nil, []}

  defp linear(axis),
    do:
      {"Linear", "robot_#{String.downcase(axis)}", axis,
       [
         {"pos", "POSITION", "Position", :sample, "MILLIMETER",
          sub_type: "ACTUAL", deadband: 0.5, name: "#{String.downcase(axis)}_pos"}
       ], []}

  defp rotary(joint),
    do:
      {"Rotary", "robot_#{String.downcase(joint)}", joint,
       [
         {"angle", "ANGLE", "Angle", :sample, "DEGREE",
          sub_type: "ACTUAL", deadband: 0.5, name: "#{String.downcase(joint)}_angle"}
       ], []}

  defp link(key, name),
    do:
      {"Adapter", "#{key}_link", name,
       [{"conn", "CONNECTION_STATUS", "ConnectionStatus", :event, nil, []}], []}

  # {component type, key, name, [item spec], children}
  defp tree do
    [
      {"Controller", "vmc", "vmc",
       [
         @avail,
         {"mode", "CONTROLLER_MODE", "ControllerMode", :event, nil, []},
         {"msg", "MESSAGE", "Message", :event, nil, []},
         {"cmd", "MESSAGE", "Message", :event, nil, name: "command"},
         {"system", "SYSTEM", "System", :condition, nil, []}
       ],
       [
         {"Path", "vmc_path", "path",
          [
            {"exec", "EXECUTION", "Execution", :event, nil, []},
            {"program", "PROGRAM", "Program", :event, nil, []},
            {"part_count", "PART_COUNT", "PartCount", :event, nil, sub_type: "ALL"},
            # the DNC transfer's progress: see dnc_transfer/1
            {"transfer", "MESSAGE", "Message", :event, nil, name: "dnc_transfer"}
          ], []}
       ]},
      {"Controller", "robot", "robot",
       [
         @avail,
         {"mode", "CONTROLLER_MODE", "ControllerMode", :event, nil, []},
         {"msg", "MESSAGE", "Message", :event, nil, []},
         {"system", "SYSTEM", "System", :condition, nil, []}
       ],
       [
         {"Path", "robot_path", "path",
          [
            {"exec", "EXECUTION", "Execution", :event, nil, []},
            {"program", "PROGRAM", "Program", :event, nil, []},
            {"pos", "PATH_POSITION", "PathPosition", :sample, "MILLIMETER_3D",
             deadband: 0.5, sub_type: "ACTUAL"}
          ], []},
         {"Axes", "robot_axes", "arm", [],
          Enum.map(~w(X Y Z), &linear/1) ++ Enum.map(~w(J1 J2 J3 J4 J5 J6), &rotary/1)}
       ]},
      {"EndEffector", "gripper", "gripper",
       [
         @avail,
         {"state", "CHUCK_STATE", "ChuckState", :event, nil, []},
         {"gap", "LENGTH", "Length", :sample, "MILLIMETER", deadband: 0.5, name: "finger_gap"},
         {"msg", "MESSAGE", "Message", :event, nil, []},
         {"cmd", "MESSAGE", "Message", :event, nil, name: "command"},
         {"system", "SYSTEM", "System", :condition, nil, []}
       ], []},
      {"Chuck", "vise", "vise",
       [
         @avail,
         {"state", "CHUCK_STATE", "ChuckState", :event, nil, []},
         {"part", "PART_DETECT", "PartDetect", :event, nil, []},
         {"jaw", "LENGTH", "Length", :sample, "MILLIMETER", deadband: 0.5, name: "jaw_width"},
         {"force", "LINEAR_FORCE", "LinearForce", :sample, "NEWTON",
          deadband: 25.0, name: "clamp_force"},
         {"msg", "MESSAGE", "Message", :event, nil, []},
         {"cmd", "MESSAGE", "Message", :event, nil, name: "command"},
         {"system", "SYSTEM", "System", :condition, nil, []}
       ], []},
      {"Lock", "tray1", "tray1", [{"state", "LOCK_STATE", "LockState", :event, nil, []}], []},
      {"Lock", "tray2", "tray2", [{"state", "LOCK_STATE", "LockState", :event, nil, []}], []},
      {"Clamp", "pallet", "pallet",
       [
         @avail,
         {"state", "LOCK_STATE", "LockState", :event, nil, []},
         {"force1", "LINEAR_FORCE", "LinearForce", :sample, "NEWTON",
          deadband: 50.0, name: "clamp1_force"},
         {"force2", "LINEAR_FORCE", "LinearForce", :sample, "NEWTON",
          deadband: 50.0, name: "clamp2_force"},
         {"msg", "MESSAGE", "Message", :event, nil, []},
         {"cmd", "MESSAGE", "Message", :event, nil, name: "command"},
         {"system", "SYSTEM", "System", :condition, nil, []}
       ], []},
      link("wc", "wc_link"),
      link("val", "val_link"),
      link("dnc", "dnc_link"),
      link("daq1", "daq1_link"),
      link("hydraulic", "hydraulic_link")
    ]
  end

  @doc """
  The MTConnect id prefix of a workstation: its id made an XML name (letters, digits, `_`, `-`,
  `.`), with a short hash when anything had to be replaced, so two workstations never share one.
  """
  @spec device_id(term) :: String.t()
  def device_id(ws) do
    name = device_name(ws)
    clean = String.replace(name, ~r/[^A-Za-z0-9_.\-]/u, "_")

    clean =
      if clean == name,
        do: clean,
        else: clean <> "_" <> Integer.to_string(:erlang.phash2(name), 36)

    "ws_" <> clean
  end

  @doc "The MTConnect device name of a workstation: its id as text."
  @spec device_name(term) :: String.t()
  def device_name(ws) when is_binary(ws), do: ws
  def device_name(ws) when is_atom(ws) or is_integer(ws), do: to_string(ws)
  def device_name(ws), do: inspect(ws)

  @doc "The device model of a workstation."
  @spec device(term) :: device
  def device(ws) do
    id = device_id(ws)
    name = device_name(ws)
    uuid = "vws-" <> String.replace_prefix(id, "ws_", "")
    ctx = %{device: name, device_uuid: uuid, prefix: id}

    %{
      id: id,
      name: name,
      uuid: uuid,
      items: [item(ctx, "Device", id, name, @avail, "")],
      components: Enum.map(tree(), &component(ctx, &1))
    }
  end

  defp component(ctx, {type, key, name, items, children}) do
    cid = "#{ctx.prefix}_#{key}"

    %{
      type: type,
      id: cid,
      name: name,
      items: Enum.map(items, &item(ctx, type, cid, name, &1, key)),
      components: Enum.map(children, &component(ctx, &1))
    }
  end

  defp item(ctx, ctype, cid, cname, {ikey, type, element, category, units, opts}, key) do
    %{
      id: if(key == "", do: "#{ctx.prefix}_#{ikey}", else: "#{ctx.prefix}_#{key}_#{ikey}"),
      name: Keyword.get(opts, :name),
      type: type,
      sub_type: Keyword.get(opts, :sub_type),
      deadband: Keyword.get(opts, :deadband),
      category: category,
      element: element,
      units: units,
      component: ctype,
      component_id: cid,
      component_name: cname,
      device: ctx.device,
      device_uuid: ctx.device_uuid
    }
  end

  @doc """
  The agent's own device (`<Agent>`, which MTConnect 2.x agents publish beside the devices they
  serve): its availability, and the uuid of the last device added and removed.
  """
  @spec agent_device(String.t()) :: device
  def agent_device(sender) do
    clean = String.replace(sender, ~r/[^A-Za-z0-9_.\-]/u, "_")
    ctx = %{device: "Agent", device_uuid: "vws-agent-" <> clean, prefix: "agent"}

    %{
      kind: "Agent",
      id: "agent",
      name: "Agent",
      uuid: ctx.device_uuid,
      items:
        for spec <- [
              @avail,
              {"device_added", "DEVICE_ADDED", "DeviceAdded", :event, nil, []},
              {"device_removed", "DEVICE_REMOVED", "DeviceRemoved", :event, nil, []}
            ] do
          item(ctx, "Agent", "agent", "Agent", spec, "")
        end,
      components: []
    }
  end

  @doc "Every data item of a device, depth first."
  @spec items(device | component) :: [item]
  def items(%{items: items, components: components}),
    do: items ++ Enum.flat_map(components, &items/1)

  # The status texts whose items depend on that text alone (text_values/3)
  @text_only ["GRIPPER", "VISE", "TRAYS"]

  @doc """
  The value of every data item of a workstation's device from what is known of it (`nil`: the
  workstation cannot be read, every item `UNAVAILABLE`). Returns `%{item_id => value}`.
  """
  @spec observe(device, facts | nil) :: %{String.t() => value}
  def observe(device, nil) do
    Map.new(items(device), fn
      %{category: :condition} = i -> {i.id, unavailable_condition()}
      i -> {i.id, @unavailable}
    end)
  end

  def observe(device, facts) do
    texts = Map.get(facts, :devices, %{})
    text = fn name -> Map.get(texts, name) end
    commands = Map.get(facts, :commands, %{})
    cmd_in = Map.get(facts, :cmd_in, %{})
    readings = Map.get(facts, :readings, %{})
    links = Map.get(facts, :links, %{})
    status = fn p -> Map.get(commands, p, {nil, :none}) end
    monarch = text.("MONARCH")
    {_n, robot_status} = status.(:robot)
    report = readings[:monarch]
    vmc? = vmc_available?(monarch)
    world = robot_numbers(text.("WHERE_ROBOT"))
    robot? = links[:val] == "ESTABLISHED" or world != nil or robot_status in [:executing, :done]
    sensors = if match?(%Vws.Links.DAQ.Readings{}, texts["SENSORS"]), do: texts["SENSORS"]
    daq? = sensors != nil
    pallet = readings[:pallet]
    pallet? = pallet_state(text.("PALLET")) != @unavailable
    p = device.id

    at = fn i ->
      case world do
        nums when is_list(nums) and length(nums) > i -> Enum.at(nums, i)
        _ -> @unavailable
      end
    end

    values = %{
      "#{p}_avail" => "AVAILABLE",
      "#{p}_vmc_avail" => available(vmc?),
      "#{p}_vmc_mode" => if(vmc?, do: "AUTOMATIC", else: @unavailable),
      "#{p}_vmc_msg" => message(monarch),
      "#{p}_vmc_cmd" => command_message(status.(:monarch), cmd_in[:monarch], true),
      "#{p}_vmc_system" => vmc_condition(vmc?, report, status.(:monarch)),
      "#{p}_vmc_path_exec" => vmc_execution(monarch),
      "#{p}_vmc_path_program" => vmc_program(report, Map.get(facts, :program)),
      "#{p}_vmc_path_part_count" =>
        if(vmc?, do: Integer.to_string(Map.get(facts, :part_count, 0)), else: @unavailable),
      "#{p}_vmc_path_transfer" => dnc_transfer(facts),
      "#{p}_robot_avail" => available(robot?),
      "#{p}_robot_mode" => if(robot?, do: "AUTOMATIC", else: @unavailable),
      "#{p}_robot_msg" => command_message(status.(:robot), cmd_in[:robot], robot?),
      "#{p}_robot_system" => command_condition(status.(:robot), robot?),
      "#{p}_robot_path_exec" => if(robot?, do: robot_execution(robot_status), else: @unavailable),
      "#{p}_robot_path_program" => robot_program(cmd_in[:robot]),
      "#{p}_robot_path_pos" =>
        if(world,
          do: Enum.map_join(Enum.take(world, 3), " ", &format_number/1),
          else: @unavailable
        ),
      "#{p}_robot_x_pos" => at.(0),
      "#{p}_robot_y_pos" => at.(1),
      "#{p}_robot_z_pos" => at.(2),
      "#{p}_robot_j1_angle" => at.(6),
      "#{p}_robot_j2_angle" => at.(7),
      "#{p}_robot_j3_angle" => at.(8),
      "#{p}_robot_j4_angle" => at.(9),
      "#{p}_robot_j5_angle" => at.(10),
      "#{p}_robot_j6_angle" => at.(11),
      "#{p}_gripper_avail" => available(daq?),
      "#{p}_gripper_cmd" => command_message(status.(:gripper), cmd_in[:gripper], true),
      "#{p}_gripper_system" => command_condition(status.(:gripper), daq?),
      "#{p}_vise_avail" => available(daq?),
      "#{p}_vise_cmd" => command_message(status.(:fixture), cmd_in[:fixture], true),
      "#{p}_vise_system" => command_condition(status.(:fixture), daq?),
      "#{p}_pallet_avail" => available(pallet?),
      "#{p}_pallet_state" => pallet_state(text.("PALLET")),
      "#{p}_pallet_force1" => pallet_force(pallet?, pallet, :force1_n),
      "#{p}_pallet_force2" => pallet_force(pallet?, pallet, :force2_n),
      "#{p}_pallet_msg" => message(text.("PALLET")),
      "#{p}_pallet_cmd" => command_message(status.(:hydraulic), cmd_in[:hydraulic], true),
      "#{p}_pallet_system" => command_condition(status.(:hydraulic), pallet?),
      "#{p}_wc_link_conn" => Map.get(links, :wc, @unavailable),
      "#{p}_val_link_conn" => Map.get(links, :val, @unavailable),
      "#{p}_dnc_link_conn" => Map.get(links, :dnc, @unavailable),
      "#{p}_daq1_link_conn" => Map.get(links, :daq1, @unavailable),
      "#{p}_hydraulic_link_conn" => Map.get(links, :hydraulic, @unavailable)
    }

    values =
      Enum.reduce(@text_only, Map.merge(values, sensor_values(p, sensors)), fn name, acc ->
        Map.merge(acc, text_values(p, name, text.(name)))
      end)

    Map.new(items(device), fn i ->
      default = if i.category == :condition, do: unavailable_condition(), else: @unavailable
      {i.id, Map.get(values, i.id, default)}
    end)
  end

  @doc """
  What one change of a workstation's facts does to its data items, when it touches only a few:
  `{:only, %{item_id => value}}` — those items' new values, every other item's value the same as
  `observe/2` gave before the change — or `:all` (observe the whole device again). `change` is
  `{:device, loc, value}` (a status location by its number or name) or anything else; `before` what was
  known before it. A poll of DAQ #1 changes SENSORS (a new reading) and often VISE (the force in
  its text): their few items are worked out alone, not the device's 54.
  """
  @spec changed_values(device, term, facts) :: {:only, %{String.t() => value}} | :all
  def changed_values(device, {:device, loc, value}, before) when is_integer(loc),
    do: changed_values(device, {:device, Vws.CEC.Mailbox.device_name(loc), value}, before)

  def changed_values(%{id: p}, {:device, "SENSORS", %Vws.Links.DAQ.Readings{} = new}, before) do
    # (whether there are readings at all decides the gripper's and the vise's availability)
    case get_in(before, [:devices, "SENSORS"]) do
      %Vws.Links.DAQ.Readings{} -> {:only, sensor_values(p, new)}
      _ -> :all
    end
  end

  def changed_values(%{id: p}, {:device, name, new}, _before) when name in @text_only,
    do: {:only, text_values(p, name, new)}

  def changed_values(_device, _change, _before), do: :all

  # the items read from DAQ #1's readings (nil: none)
  defp sensor_values(p, sensors) do
    %{
      "#{p}_gripper_gap" => reading(sensors, :gripper_finger_mm),
      "#{p}_vise_jaw" => reading(sensors, :vise_jaw_mm),
      "#{p}_vise_force" => reading(sensors, :vise_force_n)
    }
  end

  # the items read from one status text alone
  defp text_values(p, "GRIPPER", text),
    do: %{"#{p}_gripper_state" => gripper_state(text), "#{p}_gripper_msg" => message(text)}

  defp text_values(p, "VISE", text) do
    %{
      "#{p}_vise_state" => vise_state(text),
      "#{p}_vise_part" => vise_part(text),
      "#{p}_vise_msg" => message(text)
    }
  end

  defp text_values(p, "TRAYS", text),
    do: %{"#{p}_tray1_state" => tray_state(text, 1), "#{p}_tray2_state" => tray_state(text, 2)}

  @doc """
  The DNC transfer message: what the GE-2000 link is transferring or transferred last
  (`facts.transfer`, from the link's `:dnc_progress` events: `transfer_text/1`), else
  `UNAVAILABLE`.
  """
  @spec dnc_transfer(facts) :: String.t()
  def dnc_transfer(facts) do
    case Map.get(facts, :transfer) do
      text when is_binary(text) and text != "" -> text
      _ -> @unavailable
    end
  end

  @doc """
  A DNC transfer's progress (the payload of `:dnc_progress`, `Vws.Links.DNC`) as the VMC's
  transfer message.

      iex> Vws.Ops.MTConnect.Model.transfer_text(%{program: "001234.PRO", operation: :part_program,
      ...>   direction: :out, bytes: 1200, total_bytes: 5000, retries: 1, ended: false})
      "SENDING 001234.PRO 1200/5000 BYTES, 1 RETRY"
      iex> Vws.Ops.MTConnect.Model.transfer_text(%{program: "000100.PRO", operation: :part_program,
      ...>   direction: :in, bytes: 800, total_bytes: nil, retries: 0, ended: :ok})
      "RECEIVED 000100.PRO 800 BYTES"
      iex> Vws.Ops.MTConnect.Model.transfer_text(%{program: "000007.PRO", operation: :download_execute,
      ...>   direction: :out, bytes: 300, total_bytes: 900, retries: 4, ended: :link_down})
      "DRIP FEED 000007.PRO FAILED AT 300/900 BYTES (LINK_DOWN), 4 RETRIES"
      iex> Vws.Ops.MTConnect.Model.transfer_text(%{program: "000007.PRO", operation: :download_execute,
      ...>   direction: :out, bytes: 600, total_bytes: 900, retries: 0, pauses: 3, ended: false})
      "DRIP FEED 000007.PRO 600/900 BYTES, 3 PAUSES"
  """
  @spec transfer_text(map) :: String.t()
  def transfer_text(p) do
    what =
      case {p[:operation], p[:direction], p[:ended]} do
        {:download_execute, _, _} -> "DRIP FEED"
        {_, :out, false} -> "SENDING"
        {_, :out, _} -> "SENT"
        {_, _, false} -> "RECEIVING"
        {_, _, _} -> "RECEIVED"
      end

    bytes =
      if is_integer(p[:total_bytes]),
        do: "#{p[:bytes]}/#{p[:total_bytes]} BYTES",
        else: "#{p[:bytes]} BYTES"

    retries =
      case p[:retries] || 0 do
        0 -> ""
        1 -> ", 1 RETRY"
        n -> ", #{n} RETRIES"
      end

    # WACKs: the machine asked the CEC to wait (a drip feed's flow control), not a fault
    retries =
      case p[:pauses] || 0 do
        0 -> retries
        1 -> retries <> ", 1 PAUSE"
        n -> retries <> ", #{n} PAUSES"
      end

    # the seed's DOWNLOAD_GE names no program on the line: the NC file
    program = if p[:program] in [nil, ""], do: "NC FILE", else: p[:program]

    case p[:ended] do
      e when e in [false, :ok] ->
        "#{what} #{program} #{bytes}#{retries}"

      reason ->
        why =
          cond do
            is_exception(reason) -> Exception.message(reason)
            is_atom(reason) -> Atom.to_string(reason)
            is_binary(reason) -> reason
            true -> inspect(reason, limit: 3)
          end
          |> String.upcase()

        "#{what} #{program} FAILED AT #{bytes} (#{why})#{retries}"
    end
  end

  defp unavailable_condition, do: {:condition, "Unavailable", nil, ""}
  defp normal_condition, do: {:condition, "Normal", nil, ""}

  # the GE-2000's alarm (its status report) is a fault with the alarm number as native code;
  # else the MONARCH command's error
  defp vmc_condition(false, _report, _status), do: unavailable_condition()

  defp vmc_condition(true, %{alarm: alarm}, _status) when is_integer(alarm) and alarm > 0,
    do: {:condition, "Fault", Integer.to_string(alarm), "GE-2000 ALARM #{alarm}"}

  defp vmc_condition(true, _report, status), do: command_condition(status, true)

  @doc """
  A partition's condition from its last command: `Fault` while that command ended `ERROR`
  (native code: the device's own error number when the reason starts with one, as the VAL II's
  `-601 …`, else `CEC`), `Normal` otherwise.

      iex> Vws.Ops.MTConnect.Model.command_condition({7, {:error, "-601 POSITION OUT OF REACH"}}, true)
      {:condition, "Fault", "-601", "0007 ERROR -601 POSITION OUT OF REACH"}
      iex> Vws.Ops.MTConnect.Model.command_condition({8, :done}, true)
      {:condition, "Normal", nil, ""}
  """
  @spec command_condition({integer | nil, term}, boolean) :: value
  def command_condition(_status, false), do: unavailable_condition()

  def command_condition({n, {:error, reason}}, true) when is_binary(reason) do
    code =
      case Regex.run(~r/^\s*(-?\d+)\b/, reason) do
        [_, code] -> code
        nil -> "CEC"
      end

    {:condition, "Fault", code, "#{number(n)} ERROR #{reason}"}
  end

  def command_condition(_status, true), do: normal_condition()

  @doc """
  A partition's Message: its latest command's number, text and status as the WC reads them
  (`0012 DO MOVE TRAY1 EXECUTING`); `NO COMMAND YET` before any.
  """
  @spec command_message({integer | nil, term}, String.t() | nil, boolean) :: String.t()
  def command_message({nil, _}, _text, true), do: "NO COMMAND YET"
  def command_message({nil, _}, _text, false), do: @unavailable

  def command_message({n, status}, text, _available?) do
    [number(n), text, Vws.CEC.Mailbox.status_word(status)]
    |> Enum.reject(&(&1 in [nil, ""]))
    |> Enum.join(" ")
  end

  defp number(nil), do: "----"
  defp number(n), do: n |> Integer.to_string() |> String.pad_leading(4, "0")

  # the program the robot runs: the name in its last EXECUTE
  defp robot_program(text) when is_binary(text) do
    case Regex.run(~r/^\s*EXECUTE\s+(\S+)/, text) do
      [_, name] -> name
      nil -> @unavailable
    end
  end

  defp robot_program(_), do: @unavailable

  # the GE-2000's own report names the program it has (000000: none); else the last selected
  defp vmc_program(%{program: program}, _selected) when is_binary(program) do
    if program =~ ~r/^0*$/, do: @unavailable, else: program
  end

  defp vmc_program(_report, selected), do: selected || @unavailable

  defp reading(%Vws.Links.DAQ.Readings{} = r, signal) do
    case Vws.Links.DAQ.Readings.get(r, signal) do
      v when is_number(v) -> v * 1.0
      _ -> @unavailable
    end
  end

  defp reading(_, _), do: @unavailable

  defp pallet_force(true, %{} = pallet, key) do
    case Map.get(pallet, key) do
      v when is_number(v) and v < 1.0e6 -> v * 1.0
      _ -> @unavailable
    end
  end

  defp pallet_force(_, _, _), do: @unavailable

  @doc """
  Whether a new value of an item is worth recording after `last`: any change of an event or a
  condition; for a sample, a move of at least its deadband (or to or from `UNAVAILABLE`); for a
  message, a change of its words or of one of its numbers by at least 0.5 (so the ±0.1 mm
  noise in `VISE JAWS ARE 50.0 MM APART` does not count).

      iex> i = %{category: :sample, deadband: 0.5, type: "LENGTH"}
      iex> {Vws.Ops.MTConnect.Model.changed?(i, 50.0, 50.3), Vws.Ops.MTConnect.Model.changed?(i, 50.0, 50.6)}
      {false, true}
      iex> m = %{category: :event, deadband: nil, type: "MESSAGE"}
      iex> Vws.Ops.MTConnect.Model.changed?(m, "VISE JAWS ARE 50.0 MM APART", "VISE JAWS ARE 50.1 MM APART")
      false
  """
  @spec changed?(item, value | nil, value) :: boolean
  def changed?(_item, same, same), do: false
  def changed?(_item, nil, _new), do: true

  def changed?(%{category: :sample, deadband: band}, old, new)
      when is_number(old) and is_number(new) and is_number(band),
      do: abs(new - old) >= band

  def changed?(%{category: :sample, deadband: band}, old, new)
      when is_binary(old) and is_binary(new) and is_number(band) do
    case {vector(old), vector(new)} do
      {[_ | _] = a, [_ | _] = b} when length(a) == length(b) ->
        Enum.zip(a, b) |> Enum.any?(fn {x, y} -> abs(x - y) >= band end)

      _ ->
        true
    end
  end

  def changed?(%{type: "MESSAGE"}, old, new) when is_binary(old) and is_binary(new) do
    {words_a, nums_a} = split_numbers(old)
    {words_b, nums_b} = split_numbers(new)

    words_a != words_b or length(nums_a) != length(nums_b) or
      Enum.zip(nums_a, nums_b) |> Enum.any?(fn {x, y} -> abs(x - y) >= 0.5 end)
  end

  def changed?(_item, _old, _new), do: true

  defp vector(text) do
    parts = String.split(text, " ", trim: true)
    nums = for p <- parts, {f, ""} <- [Float.parse(p)], do: f
    if length(nums) == length(parts), do: nums, else: []
  end

  defp split_numbers(text) do
    tokens = String.split(text, ~r/(-?\d+(?:\.\d+)?)/, include_captures: true)

    Enum.reduce(tokens, {[], []}, fn t, {words, nums} ->
      case Float.parse(t) do
        {f, ""} -> {[:number | words], [f | nums]}
        _ -> {[t | words], nums}
      end
    end)
  end

  defp available(true), do: "AVAILABLE"
  defp available(false), do: @unavailable

  @doc "True when the MONARCH status text is a reading from the VMC (`ACTIVE` or `IDLE`)."
  @spec vmc_available?(term) :: boolean
  def vmc_available?(text), do: vmc_execution(text) != @unavailable

  @doc "The VMC's Execution from the MONARCH status text."
  @spec vmc_execution(term) :: String.t()
  def vmc_execution("ACTIVE" <> _), do: "ACTIVE"
  def vmc_execution("IDLE" <> _), do: "READY"
  def vmc_execution(_), do: @unavailable

  @doc "The robot's Execution from its command status."
  @spec robot_execution(term) :: String.t()
  def robot_execution(:executing), do: "ACTIVE"
  def robot_execution(:done), do: "READY"
  def robot_execution(:none), do: "READY"
  def robot_execution({:error, _}), do: "STOPPED"
  def robot_execution(_), do: @unavailable

  @doc """
  The robot's position `"x y z"` from WHERE_ROBOT (`x/y/z/θ/A/T/j1/…`), or nil when the text is
  not a position.
  """
  @spec robot_position(term) :: String.t() | nil
  def robot_position(text) when is_binary(text) do
    with [x, y, z | _] <- String.split(text, ["/", ","]),
         {:ok, nums} <- numbers([x, y, z]) do
      Enum.map_join(nums, " ", &format_number/1)
    else
      _ -> nil
    end
  end

  def robot_position(_), do: nil

  @doc "Every number of WHERE_ROBOT (`x/y/z/o/a/t/j1/…/j6`), or nil when the text is not a position."
  @spec robot_numbers(term) :: [float] | nil
  def robot_numbers(text) when is_binary(text) do
    case numbers(String.split(text, ["/", ","])) do
      {:ok, [_, _, _ | _] = nums} -> nums
      _ -> nil
    end
  end

  def robot_numbers(_), do: nil

  defp numbers(strings) do
    Enum.reduce_while(strings, {:ok, []}, fn s, {:ok, acc} ->
      case Float.parse(String.trim(s)) do
        {f, ""} -> {:cont, {:ok, acc ++ [f]}}
        _ -> {:halt, :error}
      end
    end)
  end

  defp format_number(f) when f == trunc(f), do: Integer.to_string(trunc(f))
  defp format_number(f), do: :erlang.float_to_binary(f, [:short])

  @doc "The gripper's ChuckState from the GRIPPER status text."
  @spec gripper_state(term) :: String.t()
  def gripper_state(text) when is_binary(text) do
    cond do
      no_data?(text) -> @unavailable
      text =~ "IS OPEN" -> "OPEN"
      text =~ "CLOSED" or String.starts_with?(text, "FINGERS ARE") -> "CLOSED"
      true -> @unavailable
    end
  end

  def gripper_state(_), do: @unavailable

  @doc "The vise's ChuckState from the VISE status text."
  @spec vise_state(term) :: String.t()
  def vise_state(text) when is_binary(text) do
    cond do
      no_data?(text) -> @unavailable
      text =~ "UNLOCKED" -> "OPEN"
      text =~ "LOCKED" -> "CLOSED"
      true -> @unavailable
    end
  end

  def vise_state(_), do: @unavailable

  @doc "The vise's PartDetect from the VISE status text."
  @spec vise_part(term) :: String.t()
  def vise_part(text) when is_binary(text) do
    cond do
      no_data?(text) -> @unavailable
      text =~ "PART NOT IN VISE" -> "NOT_PRESENT"
      text =~ "PART IN VISE" -> "PRESENT"
      true -> @unavailable
    end
  end

  def vise_part(_), do: @unavailable

  @doc "Tray `n`'s LockState from the TRAYS status text."
  @spec tray_state(term, pos_integer) :: String.t()
  # (one regex compiled with the module: one with `n` interpolated was compiled at every status)
  def tray_state(text, n) when is_binary(text) do
    tray = Integer.to_string(n)

    case Enum.find(
           Regex.scan(~r/TRAY #?(\d+) (NOT )?IN POSITION/, text),
           &(Enum.at(&1, 1) == tray)
         ) do
      [_, _, "NOT "] -> "UNLOCKED"
      [_, _] -> "LOCKED"
      _ -> @unavailable
    end
  end

  def tray_state(_, _), do: @unavailable

  @doc "The pallet clamp's LockState from the PALLET status text."
  @spec pallet_state(term) :: String.t()
  def pallet_state(text) when is_binary(text) do
    cond do
      text =~ "NOT CLAMPED" or text =~ "UNCLAMPED" -> "UNLOCKED"
      text =~ ~r/^PALLET (IS )?CLAMPED/ -> "LOCKED"
      true -> @unavailable
    end
  end

  def pallet_state(_), do: @unavailable

  @doc "A Message value: the status text itself, `UNAVAILABLE` when there is none."
  @spec message(term) :: String.t()
  def message(text) when is_binary(text) and text != "", do: text
  def message({:no_data, why}) when is_binary(why), do: "NO DATA (#{why})"
  def message(_), do: @unavailable

  @doc """
  The program the VMC runs: the number in `PROGRAM_SELECT(n)` when that is the Monarch's latest
  command, else the one known before.
  """
  @spec program(String.t() | nil, String.t() | nil) :: String.t() | nil
  def program(cmd_text, previous) when is_binary(cmd_text) do
    case Regex.run(~r/^\s*PROGRAM_SELECT\s*\(\s*([^)\s]+)\s*\)/, cmd_text) do
      [_, program] -> program
      nil -> previous
    end
  end

  def program(_, previous), do: previous

  defp no_data?(text), do: String.starts_with?(text, "NO DATA")
end
