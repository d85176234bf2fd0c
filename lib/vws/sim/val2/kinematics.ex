defmodule Vws.Sim.VAL2.Kinematics do
  @moduledoc """
  Poses and the polar-arm model of the simulated VAL II robot (a Unimate-style hydraulic arm).
  Pure: no processes.

  A pose is a position `{x, y, z}` in mm and a rotation matrix. Locations are written as VAL II
  writes them, `{x, y, z, o, a, t}`: the position and the Euler angles O, A, T in degrees, the
  rotation being `Rz(O)·Ry(A)·Rz(T)`. The tool points along its own Z axis; APPRO and DEPART
  offset along it. A compound transformation `loc:TRANS(…)` is `loc` composed with the
  transformation (`compose/2`): its position is taken in `loc`'s frame.

  ## The arm (geometry from `priv/sims/robot_locations.exs`, key `arm`)

    * j1 — base rotation about the world Z axis, degrees;
    * j2 — pitch of the boom about a horizontal axis at `shoulder_height` above the floor,
      degrees, positive up;
    * j3 — boom extension, mm: the wrist centre lies `boom_retracted + j3` from the pitch axis;
    * j4, j5, j6 — the three wrist axes: the Z-Y-Z Euler angles of the tool rotation relative to
      the boom (base rotation then pitch), degrees.

  The tool point lies `tool_length` beyond the wrist centre along the tool Z axis. A pose is out
  of reach when j1, j2 or j3 leaves its range; the wrist reaches every orientation.

      iex> arm = %{shoulder_height: 1000.0, boom_retracted: 650.0, tool_length: 250.0,
      ...>   base: {-150.0, 150.0}, pitch: {-45.0, 35.0}, boom_stroke: {0.0, 900.0}}
      iex> pose = Vws.Sim.VAL2.Kinematics.pose({1200.0, 0.0, 850.0, 0.0, 180.0, 0.0})
      iex> {:ok, [j1, j2, j3 | _]} = Vws.Sim.VAL2.Kinematics.joints(pose, arm)
      iex> {Float.round(j1, 1), Float.round(j2, 2), Float.round(j3, 1)}
      {0.0, 4.76, 554.2}
  """

  @type vector :: {float, float, float}
  @type rotation :: {vector, vector, vector}
  @type pose :: %{position: vector, rotation: rotation}
  @type location :: {number, number, number, number, number, number}

  @eps 1.0e-9

  @doc "The pose of a location `{x, y, z, o, a, t}`."
  @spec pose(location) :: pose
  def pose({x, y, z, o, a, t}) do
    %{position: {x * 1.0, y * 1.0, z * 1.0}, rotation: euler(o, a, t)}
  end

  @doc "The location `{x, y, z, o, a, t}` of a pose, with A in 0..180 (VAL II's form)."
  @spec location(pose) :: location
  def location(%{position: {x, y, z}, rotation: r}) do
    {o, a, t} = to_euler(r)
    {x, y, z, o, a, t}
  end

  @doc "`Rz(o)·Ry(a)·Rz(t)`, angles in degrees."
  @spec euler(number, number, number) :: rotation
  def euler(o, a, t), do: mul(mul(rz(o), ry(a)), rz(t))

  @doc "The Z-Y-Z Euler angles `{o, a, t}` of a rotation, A in 0..180 degrees."
  @spec to_euler(rotation) :: {float, float, float}
  def to_euler({{r11, _r12, r13}, {r21, r22, r23}, {r31, r32, r33}}) do
    sin_a = :math.sqrt(r13 * r13 + r23 * r23)

    cond do
      sin_a > 1.0e-6 ->
        {deg(:math.atan2(r23, r13)), deg(:math.atan2(sin_a, r33)), deg(:math.atan2(r32, -r31))}

      r33 > 0 ->
        {0.0, 0.0, deg(:math.atan2(r21, r11))}

      true ->
        {0.0, 180.0, -deg(:math.atan2(-r21, r22))}
    end
    |> clean()
  end

  @doc "`base` composed with `relative`: `relative`'s position and rotation taken in `base`'s frame."
  @spec compose(pose, pose) :: pose
  def compose(%{position: p, rotation: r}, %{position: q, rotation: s}) do
    %{position: add(p, apply_rotation(r, q)), rotation: mul(r, s)}
  end

  @doc "The pose moved `distance` mm along its own tool Z axis (negative: back, as DEPART does)."
  @spec along_tool(pose, number) :: pose
  def along_tool(%{position: p, rotation: r} = pose, distance) do
    %{pose | position: add(p, scale(tool_z(r), distance))}
  end

  @doc "The tool Z axis (approach direction) of a rotation, in world coordinates."
  @spec tool_z(rotation) :: vector
  def tool_z({{_, _, r13}, {_, _, r23}, {_, _, r33}}), do: {r13, r23, r33}

  @doc """
  The joint values `[j1, …, j6]` of a pose, or `{:error, {joint, value}}` naming the first of j1,
  j2, j3 outside its range.
  """
  @spec joints(pose, map) :: {:ok, [float]} | {:error, {1..3, float}}
  def joints(%{position: p, rotation: r}, arm) do
    {wx, wy, wz} = sub(p, scale(tool_z(r), arm.tool_length))
    rho = :math.sqrt(wx * wx + wy * wy)
    h = wz - arm.shoulder_height
    j1 = if rho < @eps, do: 0.0, else: deg(:math.atan2(wy, wx))
    j2 = deg(:math.atan2(h, rho))
    j3 = :math.sqrt(rho * rho + h * h) - arm.boom_retracted
    boom = mul(rz(j1), ry(-j2))
    {j4, j5, j6} = to_euler(mul(transpose(boom), r))

    cond do
      not within?(j1, arm.base) -> {:error, {1, j1}}
      not within?(j2, arm.pitch) -> {:error, {2, j2}}
      not within?(j3, arm.boom_stroke) -> {:error, {3, j3}}
      true -> {:ok, Enum.map([j1, j2, j3, j4, j5, j6], &clean_number/1)}
    end
  end

  @doc "The pose of joint values `[j1, …, j6]` (forward kinematics; no range check)."
  @spec forward([number], map) :: pose
  def forward([j1, j2, j3, j4, j5, j6], arm) do
    boom = mul(rz(j1), ry(-j2))

    wrist =
      add(
        {0.0, 0.0, arm.shoulder_height},
        apply_rotation(boom, {arm.boom_retracted + j3, 0.0, 0.0})
      )

    rotation = mul(boom, euler(j4, j5, j6))
    %{position: add(wrist, scale(tool_z(rotation), arm.tool_length)), rotation: rotation}
  end

  @doc "The straight-line distance between two poses' positions, mm."
  @spec distance(pose, pose) :: float
  def distance(%{position: p}, %{position: q}), do: norm(sub(p, q))

  @doc "The angle of the rotation taking one pose's orientation to the other's, degrees."
  @spec rotation_angle(pose, pose) :: float
  def rotation_angle(%{rotation: r}, %{rotation: s}) do
    {{a, _, _}, {_, b, _}, {_, _, c}} = mul(transpose(r), s)
    cos = min(max((a + b + c - 1) / 2, -1.0), 1.0)
    deg(:math.acos(cos))
  end

  @doc "The pose a fraction `f` (0..1) of the way along the straight line from `from` to `to`."
  @spec interpolate(pose, pose, float) :: pose
  def interpolate(%{position: p} = from, %{position: q, rotation: s}, f) do
    rotation = if f >= 1.0, do: s, else: from.rotation
    %{position: add(p, scale(sub(q, p), f)), rotation: rotation}
  end

  @doc "The smallest difference between two angles, degrees (-180..180)."
  @spec angle_difference(number, number) :: float
  def angle_difference(a, b) do
    d = :math.fmod(a - b + 540.0, 360.0) - 180.0
    if d < -180.0, do: d + 360.0, else: d
  end

  # matrices, as tuples of rows

  defp rz(deg) do
    {c, s} = cos_sin(deg)
    {{c, -s, 0.0}, {s, c, 0.0}, {0.0, 0.0, 1.0}}
  end

  defp ry(deg) do
    {c, s} = cos_sin(deg)
    {{c, 0.0, s}, {0.0, 1.0, 0.0}, {-s, 0.0, c}}
  end

  # exact values at multiples of 90 degrees, so named locations come back as written
  defp cos_sin(deg) do
    r = :math.fmod(deg * 1.0, 360.0)
    r = if r < 0, do: r + 360.0, else: r

    cond do
      r == 0.0 -> {1.0, 0.0}
      r == 90.0 -> {0.0, 1.0}
      r == 180.0 -> {-1.0, 0.0}
      r == 270.0 -> {0.0, -1.0}
      true -> {:math.cos(rad(deg)), :math.sin(rad(deg))}
    end
  end

  defp mul(a, b) do
    bt = transpose(b)

    a
    |> Tuple.to_list()
    |> Enum.map(fn row ->
      bt |> Tuple.to_list() |> Enum.map(&dot(row, &1)) |> List.to_tuple()
    end)
    |> List.to_tuple()
  end

  defp transpose({{a, b, c}, {d, e, f}, {g, h, i}}), do: {{a, d, g}, {b, e, h}, {c, f, i}}
  defp apply_rotation({r1, r2, r3}, v), do: {dot(r1, v), dot(r2, v), dot(r3, v)}
  defp dot({a, b, c}, {d, e, f}), do: a * d + b * e + c * f
  defp add({a, b, c}, {d, e, f}), do: {a + d, b + e, c + f}
  defp sub({a, b, c}, {d, e, f}), do: {a - d, b - e, c - f}
  defp scale({a, b, c}, k), do: {a * k, b * k, c * k}
  defp norm(v), do: :math.sqrt(dot(v, v))
  defp within?(v, {lo, hi}), do: v >= lo - 1.0e-6 and v <= hi + 1.0e-6
  defp deg(rad), do: rad * 180.0 / :math.pi()
  defp rad(deg), do: deg * :math.pi() / 180.0

  defp clean({a, b, c}), do: {clean_number(a), clean_number(b), clean_number(c)}

  # -0.0 and float dust from exact rotations read as 0
  defp clean_number(v) when abs(v) < 1.0e-9, do: 0.0
  defp clean_number(v), do: v
end
