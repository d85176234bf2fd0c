defmodule Vws.MTConnect.Model do
  @moduledoc """
  How a workstation is shown as an MTConnect device, and how its mailboxes read as MTConnect
  observations. Pure: no processes, no I/O.

  Each workstation is one `Device` (its name is the workstation id):

  ```
  Device <ws>                     Availability (the workstation runs)
  ├── Controller vmc              Availability, ControllerMode, Message (MONARCH status text)
  │   └── Path vmc_path           Execution, Program
  ├── Controller robot            Availability, Message (WHERE_ROBOT text)
  │   └── Path robot_path         Execution, PathPosition (x y z, mm)
  ├── EndEffector gripper         ChuckState, Message (GRIPPER text)
  ├── Chuck vise                  ChuckState, PartDetect, Message (VISE text)
  ├── Lock tray1, Lock tray2      LockState (tray locked in position)
  └── Clamp pallet                LockState (pallet clamped), Message (PALLET text)
  ```

  ## From mailbox texts to MTConnect values

  | item | rule |
  |------|------|
  | VMC availability | `AVAILABLE` when MONARCH reads `ACTIVE…`/`IDLE…`, else `UNAVAILABLE` |
  | VMC execution | MONARCH `ACTIVE` → `ACTIVE`, `IDLE` → `READY` |
  | VMC controller mode | `AUTOMATIC` (under DNC) while the VMC is available |
  | VMC program | the last `PROGRAM_SELECT(n)` commanded, else `UNAVAILABLE` |
  | robot availability | WHERE_ROBOT holds a position, or a robot command is executing or done |
  | robot execution | robot command `EXECUTING` → `ACTIVE`, `DONE`/none → `READY`, `ERROR` → `STOPPED` |
  | robot position | the first three numbers of WHERE_ROBOT (`x/y/z/…`) |
  | gripper | `…IS OPEN…` → `OPEN`; `…CLOSED…` or `FINGERS ARE…` → `CLOSED` |
  | vise | `…UNLOCKED…` → `OPEN`, `…LOCKED…` → `CLOSED`; `PART IN VISE` → `PRESENT`, `PART NOT IN VISE` → `NOT_PRESENT` |
  | trays | `TRAY #n IN POSITION` → `LOCKED`, `TRAY #n NOT IN POSITION` → `UNLOCKED` |
  | pallet | `PALLET CLAMPED` → `LOCKED`, `PALLET NOT CLAMPED` → `UNLOCKED` |

  Anything else, and every `NO DATA …`, is `UNAVAILABLE`: the agent never guesses.

      iex> Vws.MTConnect.Model.vise_state("VISE JAWS ARE 0 MM APART AND VISE IS LOCKED PART IN VISE")
      "CLOSED"
      iex> Vws.MTConnect.Model.tray_state("TRAY #1 IN POSITION TRAY #2 NOT IN POSITION", 2)
      "UNLOCKED"
  """

  @unavailable "UNAVAILABLE"

  @typedoc "One data item of the device model."
  @type item :: %{
          id: String.t(),
          type: String.t(),
          category: :event | :sample,
          element: String.t(),
          units: String.t() | nil,
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

  @typedoc "What the agent read from a workstation's mailboxes."
  @type facts :: %{
          devices: %{String.t() => term},
          commands: %{atom => {non_neg_integer | nil, term}},
          program: String.t() | nil
        }

  # {component type, key, name, [{key, type, element, category, units}], children}
  @tree [
    {"Controller", "vmc", "vmc",
     [
       {"avail", "AVAILABILITY", "Availability", :event, nil},
       {"mode", "CONTROLLER_MODE", "ControllerMode", :event, nil},
       {"msg", "MESSAGE", "Message", :event, nil}
     ],
     [
       {"Path", "vmc_path", "path",
        [
          {"exec", "EXECUTION", "Execution", :event, nil},
          {"program", "PROGRAM", "Program", :event, nil}
        ], []}
     ]},
    {"Controller", "robot", "robot",
     [
       {"avail", "AVAILABILITY", "Availability", :event, nil},
       {"msg", "MESSAGE", "Message", :event, nil}
     ],
     [
       {"Path", "robot_path", "path",
        [
          {"exec", "EXECUTION", "Execution", :event, nil},
          {"pos", "PATH_POSITION", "PathPosition", :sample, "MILLIMETER_3D"}
        ], []}
     ]},
    {"EndEffector", "gripper", "gripper",
     [
       {"state", "CHUCK_STATE", "ChuckState", :event, nil},
       {"msg", "MESSAGE", "Message", :event, nil}
     ], []},
    {"Chuck", "vise", "vise",
     [
       {"state", "CHUCK_STATE", "ChuckState", :event, nil},
       {"part", "PART_DETECT", "PartDetect", :event, nil},
       {"msg", "MESSAGE", "Message", :event, nil}
     ], []},
    {"Lock", "tray1", "tray1", [{"state", "LOCK_STATE", "LockState", :event, nil}], []},
    {"Lock", "tray2", "tray2", [{"state", "LOCK_STATE", "LockState", :event, nil}], []},
    {"Clamp", "pallet", "pallet",
     [
       {"state", "LOCK_STATE", "LockState", :event, nil},
       {"msg", "MESSAGE", "Message", :event, nil}
     ], []}
  ]

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
      items: [
        item(ctx, "Device", id, name, {"avail", "AVAILABILITY", "Availability", :event, nil}, "")
      ],
      components: Enum.map(@tree, &component(ctx, &1))
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

  defp item(ctx, ctype, cid, cname, {ikey, type, element, category, units}, key) do
    %{
      id: if(key == "", do: "#{ctx.prefix}_#{ikey}", else: "#{ctx.prefix}_#{key}_#{ikey}"),
      type: type,
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
              {"avail", "AVAILABILITY", "Availability", :event, nil},
              {"device_added", "DEVICE_ADDED", "DeviceAdded", :event, nil},
              {"device_removed", "DEVICE_REMOVED", "DeviceRemoved", :event, nil}
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

  @doc """
  The value of every data item of a workstation's device, from the facts read in its mailboxes
  (`available?` false gives every item `UNAVAILABLE`). Returns `%{item_id => value}`.
  """
  @spec observe(device, facts | nil) :: %{String.t() => String.t()}
  def observe(device, nil), do: Map.new(items(device), &{&1.id, @unavailable})

  def observe(device, facts) do
    text = fn name -> Map.get(facts.devices, name) end
    monarch = text.("MONARCH")
    where = text.("WHERE_ROBOT")
    {_n, robot_status} = Map.get(facts.commands, :robot, {nil, :none})
    vmc? = vmc_available?(monarch)
    position = robot_position(where)
    robot? = position != nil or robot_status in [:executing, :done]
    p = device.id

    values = %{
      "#{p}_avail" => "AVAILABLE",
      "#{p}_vmc_avail" => available(vmc?),
      "#{p}_vmc_mode" => if(vmc?, do: "AUTOMATIC", else: @unavailable),
      "#{p}_vmc_msg" => message(monarch),
      "#{p}_vmc_path_exec" => vmc_execution(monarch),
      "#{p}_vmc_path_program" => facts.program || @unavailable,
      "#{p}_robot_avail" => available(robot?),
      "#{p}_robot_msg" => message(where),
      "#{p}_robot_path_exec" => if(robot?, do: robot_execution(robot_status), else: @unavailable),
      "#{p}_robot_path_pos" => position || @unavailable,
      "#{p}_gripper_state" => gripper_state(text.("GRIPPER")),
      "#{p}_gripper_msg" => message(text.("GRIPPER")),
      "#{p}_vise_state" => vise_state(text.("VISE")),
      "#{p}_vise_part" => vise_part(text.("VISE")),
      "#{p}_vise_msg" => message(text.("VISE")),
      "#{p}_tray1_state" => tray_state(text.("TRAYS"), 1),
      "#{p}_tray2_state" => tray_state(text.("TRAYS"), 2),
      "#{p}_pallet_state" => pallet_state(text.("PALLET")),
      "#{p}_pallet_msg" => message(text.("PALLET"))
    }

    Map.new(items(device), &{&1.id, Map.get(values, &1.id, @unavailable)})
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
  def tray_state(text, n) when is_binary(text) do
    case Regex.run(~r/TRAY #?#{n} (NOT )?IN POSITION/, text) do
      [_, "NOT "] -> "UNLOCKED"
      [_] -> "LOCKED"
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
