defmodule Vws.Sim.VAL2.Monitor do
  @moduledoc """
  The VAL II monitor of the robot simulator, as pure data: named locations, the arm's pose and
  speed, and what each monitor command does. `Vws.Sim.VAL2` runs it over the supervisory link
  and keeps the time. Pure: no processes, no clock.

  Monitor commands (VAL II syntax: arguments separated by commas):

    * `WHERE` — the pose in world coordinates and joints (see `where/1`);
    * `SPEED n` — monitor speed, a percentage (0 < n ≤ 327) of the arm's full speeds;
    * `DO MOVE loc`, `DO MOVES loc`, `DO APPRO loc, dist`, `DO APPROS loc, dist`,
      `DO DEPART dist`, `DO DEPARTS dist` — motions; the `S` forms move the tool in a straight
      line, the others interpolate the joints. `loc` is a name or `name:TRANS(x,y,z,o,a,t)`;
      APPRO stops `dist` mm back from `loc` along its tool Z axis, DEPART moves `dist` mm back
      from where the tool is;
    * `EXECUTE name` — runs a stored program (a list of motion instructions).

  A motion takes time from the distance and the speed: joint-interpolated, the slowest joint's
  travel over its full speed; straight-line, the tool's path length (and rotation) over the
  linear (and angular) speed; both divided by SPEED/100.

      iex> m = Vws.Sim.VAL2.Monitor.new(Vws.Sim.VAL2.Monitor.load_config())
      iex> {{:ok, ""}, [{:motion, plan}], _m} = Vws.Sim.VAL2.Monitor.command(m, "DO MOVE VISE")
      iex> {plan.kind, plan.target, round(plan.duration_ms)}
      {:joint, "VISE", 1145}
      iex> {reply, [], _m} = Vws.Sim.VAL2.Monitor.command(m, "DO MOVE NOWHERE")
      iex> reply
      {:error, -301, "UNDEFINED LOCATION NOWHERE"}

  ## Errors

  Numbered as VAL II numbers its messages (negative: an error); the text follows the number.

  | code  | text                                  | when |
  |-------|---------------------------------------|------|
  | -301  | `UNDEFINED LOCATION name`             | a location name not in the table |
  | -302  | `UNKNOWN COMMAND text`                | not a monitor command or instruction we know |
  | -303  | `INVALID ARGUMENT text`               | a malformed number, distance, speed or TRANS |
  | -304  | `UNDEFINED PROGRAM name`              | EXECUTE of a program not stored |
  | -610  | `LOCATION OUT OF REACH Jn value`      | the target needs j1, j2 or j3 beyond its range |
  | -611  | `STRAIGHT LINE PATH OUT OF REACH`     | a straight-line path leaves the work envelope |
  | -640  | `MOTION ALREADY IN PROGRESS`          | a DO or EXECUTE while the arm is moving |
  | -641  | `PROGRAM ALREADY RUNNING`             | a DO or EXECUTE while a program runs |
  """

  alias Vws.Sim.VAL2.Kinematics

  @path_samples 20

  defstruct [:config, :pose, :speed, :motion, :program, :location]

  @type reply :: {:ok, String.t()} | {:error, integer, String.t()}
  @type plan :: %{
          kind: :joint | :straight,
          text: String.t(),
          target: String.t(),
          from: Kinematics.pose(),
          to: Kinematics.pose(),
          duration_ms: float
        }
  @type t :: %__MODULE__{}

  @doc "Reads a locations file (default `priv/sims/robot_locations.exs`)."
  @spec load_config(Path.t() | nil) :: map
  def load_config(path \\ nil) do
    path = path || Path.join(:code.priv_dir(:vws), "sims/robot_locations.exs")
    {config, _binding} = Code.eval_file(path)
    config
  end

  @doc "A monitor at power-up: the arm at the config's `start` location, at its `speed`."
  @spec new(map) :: t
  def new(config) do
    locations = Map.new(config.locations, fn {name, loc} -> {name, Kinematics.pose(loc)} end)
    config = %{config | locations: locations}

    %__MODULE__{
      config: config,
      pose: Map.fetch!(locations, config.start),
      location: config.start,
      speed: config.speed * 1.0
    }
  end

  @doc "Runs one monitor command: its reply, the effects it starts, and the new monitor."
  @spec command(t, String.t()) ::
          {reply, [{:motion, plan} | {:program, String.t()}], t}
  def command(m, text) do
    case text |> String.trim() |> String.upcase() do
      "WHERE" ->
        {{:ok, where(m)}, [], m}

      "SPEED " <> n ->
        case Float.parse(String.trim(n)) do
          {v, ""} when v > 0 and v <= 327 -> {{:ok, ""}, [], %{m | speed: v}}
          _ -> {{:error, -303, "INVALID ARGUMENT " <> String.trim(n)}, [], m}
        end

      "DO " <> instruction ->
        with :ok <- idle(m),
             {:ok, plan} <- plan(m, String.trim(instruction)) do
          {{:ok, ""}, [{:motion, plan}], %{m | motion: plan}}
        else
          {:error, code, text} -> {{:error, code, text}, [], m}
        end

      "EXECUTE " <> name ->
        name = String.trim(name)

        with :ok <- idle(m),
             {:ok, steps} <- program(m, name) do
          {{:ok, ""}, [{:program, name}], %{m | program: %{name: name, steps: steps}}}
        else
          {:error, code, text} -> {{:error, code, text}, [], m}
        end

      other ->
        {{:error, -302, "UNKNOWN COMMAND " <> other}, [], m}
    end
  end

  @doc """
  The next step of the running program: `{:motion, plan, m}`, `{:error, code, text, m}` (the
  program stops), or `{:done, m}` when it has run to its end.
  """
  @spec next_step(t) :: {:motion, plan, t} | {:error, integer, String.t(), t} | {:done, t}
  def next_step(%{program: %{steps: []}} = m), do: {:done, %{m | program: nil}}

  def next_step(%{program: %{steps: [step | rest]} = p} = m) do
    case plan(m, step) do
      {:ok, plan} -> {:motion, plan, %{m | motion: plan, program: %{p | steps: rest}}}
      {:error, code, text} -> {:error, code, text, %{m | program: nil}}
    end
  end

  @doc "The motion in progress has reached its target."
  @spec complete_motion(t) :: t
  def complete_motion(%{motion: %{to: to, target: target}} = m),
    do: %{m | pose: to, location: target, motion: nil}

  @doc """
  The motion in progress stops a fraction (0..1) of the way (a fault, a controller restart); a
  running program stops with it.
  """
  @spec stop_motion(t, float) :: t
  def stop_motion(%{motion: nil} = m, _fraction), do: %{m | program: nil}

  def stop_motion(%{motion: %{from: from, to: to}} = m, fraction) do
    pose = Kinematics.interpolate(from, to, min(max(fraction, 0.0), 1.0))
    %{m | pose: pose, location: nil, motion: nil, program: nil}
  end

  @doc "The monitor after a controller restart: the arm stays where it is, speed back to default."
  @spec restart(t, float) :: t
  def restart(m, fraction), do: %{stop_motion(m, fraction) | speed: m.config.speed * 1.0}

  @doc "The world coordinates and joint values of the pose: `{[x, y, z, o, a, t], [j1, …, j6]}`."
  @spec coordinates(t | Kinematics.pose(), map | nil) :: {[float], [float]}
  def coordinates(%__MODULE__{pose: pose, config: config}, _), do: coordinates(pose, config.arm)

  def coordinates(pose, arm) do
    {x, y, z, o, a, t} = Kinematics.location(pose)

    joints =
      case Kinematics.joints(pose, arm) do
        {:ok, joints} -> joints
        # only reachable poses are ever reached; keep WHERE total anyway
        {:error, _} -> List.duplicate(0.0, 6)
      end

    {[x, y, z, o, a, t], joints}
  end

  @doc """
  The text of the WHERE response (after its number): a header line, the world coordinates, a
  header line, the joint values, laid out as VAL II lays them out.
  """
  @spec where(t) :: String.t()
  def where(m) do
    {world, joints} = coordinates(m, nil)

    [
      row(~w(X Y Z O A T)),
      row(Enum.map(world, &number/1)),
      row(~w(JT1 JT2 JT3 JT4 JT5 JT6)),
      row(Enum.map(joints, &number/1))
    ]
    |> Enum.join("\r\n")
  end

  @doc "The work volume holding a pose's tool point (the config's `volumes`), else `:safe`."
  @spec volume(t | Kinematics.pose(), map) :: atom
  def volume(%__MODULE__{pose: pose, config: config}, _), do: volume(pose, config)

  def volume(%{position: {x, y, z}}, config) do
    Enum.find_value(config.volumes, :safe, fn {name, {{x0, x1}, {y0, y1}, {z0, z1}}} ->
      if x >= x0 and x <= x1 and y >= y0 and y <= y1 and z >= z0 and z <= z1, do: name
    end)
  end

  defp row(cells), do: Enum.map_join(cells, &String.pad_leading(&1, 10))
  defp number(v), do: :erlang.float_to_binary(v * 1.0, decimals: 2)

  defp idle(%{program: p}) when p != nil, do: {:error, -641, "PROGRAM ALREADY RUNNING"}
  defp idle(%{motion: mo}) when mo != nil, do: {:error, -640, "MOTION ALREADY IN PROGRESS"}
  defp idle(_m), do: :ok

  defp program(m, name) do
    case Map.fetch(m.config.programs, name) do
      {:ok, steps} -> {:ok, steps}
      :error -> {:error, -304, "UNDEFINED PROGRAM " <> name}
    end
  end

  # Plans a motion instruction (without DO), VAL II syntax.
  @doc false
  def plan(m, instruction) do
    instruction = String.upcase(instruction)

    with {:ok, kind, target_name, to} <- target(m, instruction),
         :ok <- reachable(m, to),
         :ok <- path(m, kind, to) do
      {:ok,
       %{
         kind: kind,
         text: instruction,
         target: target_name,
         from: m.pose,
         to: to,
         duration_ms: duration(m, kind, to)
       }}
    end
  end

  defp target(m, instruction) do
    case String.split(instruction, " ", parts: 2) do
      [move, loc] when move in ["MOVE", "MOVES"] ->
        with {:ok, name, pose} <- location(m, String.trim(loc)),
             do: {:ok, kind(move), name, pose}

      [appro, args] when appro in ["APPRO", "APPROS"] ->
        with [loc, dist] <- split_args(args),
             {:ok, name, pose} <- location(m, loc),
             {:ok, d} <- number_arg(dist) do
          {:ok, kind(appro), nil_if_offset(name, d), Kinematics.along_tool(pose, -d)}
        else
          {:error, _, _} = e -> e
          _ -> invalid(args)
        end

      [depart, dist] when depart in ["DEPART", "DEPARTS"] ->
        with {:ok, d} <- number_arg(String.trim(dist)),
             do: {:ok, kind(depart), nil, Kinematics.along_tool(m.pose, -d)}

      _ ->
        {:error, -302, "UNKNOWN COMMAND DO " <> instruction}
    end
  end

  defp kind(word), do: if(String.ends_with?(word, "S"), do: :straight, else: :joint)
  defp nil_if_offset(name, d), do: if(d == 0, do: name, else: nil)

  # `LOC, 50` → ["LOC", "50"], the comma that separates the distance being outside TRANS(…)
  defp split_args(args) do
    case Regex.run(~r/^\s*([^,(]+(?::TRANS\([^()]*\))?)\s*,\s*(\S+)\s*$/, args) do
      [_, loc, dist] -> [String.trim(loc), dist]
      nil -> :error
    end
  end

  defp location(m, text) do
    text = String.replace(text, " ", "")

    case Regex.run(~r/^([A-Z][A-Z0-9_.]*)(?::TRANS\(([^()]*)\))?$/, text) do
      [_, name] ->
        with {:ok, pose} <- named(m, name), do: {:ok, name, pose}

      [_, name, args] ->
        values = args |> String.split(",") |> Enum.map(&number_arg/1)

        with {:ok, base} <- named(m, name),
             true <- length(values) == 6 and Enum.all?(values, &match?({:ok, _}, &1)) do
          relative = values |> Enum.map(fn {:ok, v} -> v end) |> List.to_tuple()
          {:ok, text, Kinematics.compose(base, Kinematics.pose(relative))}
        else
          {:error, _, _} = e -> e
          false -> invalid("TRANS(" <> args <> ")")
        end

      nil ->
        invalid(text)
    end
  end

  defp named(m, name) do
    case Map.fetch(m.config.locations, name) do
      {:ok, pose} -> {:ok, pose}
      :error -> {:error, -301, "UNDEFINED LOCATION " <> name}
    end
  end

  defp number_arg(text) do
    case Float.parse(String.trim(text)) do
      {v, ""} -> {:ok, v}
      _ -> invalid(text)
    end
  end

  defp invalid(text), do: {:error, -303, "INVALID ARGUMENT " <> String.trim(text)}

  defp reachable(m, pose) do
    case Kinematics.joints(pose, m.config.arm) do
      {:ok, _} ->
        :ok

      {:error, {joint, value}} ->
        {:error, -610,
         "LOCATION OUT OF REACH J#{joint} #{:erlang.float_to_binary(value, decimals: 1)}"}
    end
  end

  defp path(_m, :joint, _to), do: :ok

  defp path(m, :straight, to) do
    inside =
      Enum.all?(1..(@path_samples - 1), fn i ->
        pose = Kinematics.interpolate(m.pose, to, i / @path_samples)
        match?({:ok, _}, Kinematics.joints(pose, m.config.arm))
      end)

    if inside, do: :ok, else: {:error, -611, "STRAIGHT LINE PATH OUT OF REACH"}
  end

  defp duration(m, :joint, to) do
    arm = m.config.arm
    {:ok, from_joints} = joints_or_zero(m.pose, arm)
    {:ok, to_joints} = joints_or_zero(to, arm)

    seconds =
      [from_joints, to_joints, arm.joint_speed, 1..6]
      |> Enum.zip()
      |> Enum.map(fn
        {a, b, v, 3} -> abs(b - a) / v
        {a, b, v, _} -> abs(Kinematics.angle_difference(b, a)) / v
      end)
      |> Enum.max()

    seconds * 1000.0 * 100.0 / m.speed
  end

  defp duration(m, :straight, to) do
    arm = m.config.arm

    seconds =
      max(
        Kinematics.distance(m.pose, to) / arm.linear_speed,
        Kinematics.rotation_angle(m.pose, to) / arm.angular_speed
      )

    seconds * 1000.0 * 100.0 / m.speed
  end

  defp joints_or_zero(pose, arm) do
    case Kinematics.joints(pose, arm) do
      {:ok, j} -> {:ok, j}
      {:error, _} -> {:ok, List.duplicate(0.0, 6)}
    end
  end
end
