defmodule Vws.Sim.VAL2.KinematicsTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Sim.VAL2.Kinematics, as: K

  doctest K

  @arm %{
    shoulder_height: 1000.0,
    boom_retracted: 650.0,
    tool_length: 250.0,
    base: {-150.0, 150.0},
    pitch: {-45.0, 35.0},
    boom_stroke: {0.0, 900.0}
  }

  defp close?(a, b, eps \\ 1.0e-6)
  defp close?(a, b, eps) when is_number(a), do: abs(a - b) < eps

  defp close?(a, b, eps) when is_tuple(a),
    do: close?(Tuple.to_list(a), Tuple.to_list(b), eps)

  defp close?(a, b, eps) when is_list(a),
    do: length(a) == length(b) and Enum.all?(Enum.zip(a, b), fn {x, y} -> close?(x, y, eps) end)

  defp pose_close?(p, q),
    do: close?(p.position, q.position, 1.0e-6) and close?(p.rotation, q.rotation)

  # Expected joint values from python3 (atan2 and hypot on the wrist centre = tool point raised
  # 250 mm, gripper down), PROTOCOLS.md's j3 being the boom extension in mm.
  test "joint values of the named locations (python3)" do
    for {loc, {j1, j2, j3}} <- [
          {{800.0, 0.0, 1200.0, 0.0, 180.0, 0.0}, {0.0, 29.357753542791276, 267.8779875342909}},
          {{1200.0, 0.0, 850.0, 0.0, 180.0, 0.0}, {0.0, 4.763641690726178, 554.1594578792296}},
          {{650.0, -450.0, 700.0, 0.0, 180.0, 0.0},
           {-34.69515353123397, -3.6188832299832416, 142.14897588774306}}
        ] do
      {:ok, [a, b, c | _]} = K.joints(K.pose(loc), @arm)
      assert close?(a, j1, 1.0e-4)
      assert close?(b, j2, 1.0e-4)
      assert close?(c, j3, 1.0e-4)
    end
  end

  test "MV1:TRANS(63.5,0,0,90,-90,0) is gripper-down 300 mm above tray 1 location 3 (python3)" do
    mv1 = K.pose({650.0, -513.5, 1000.0, 180.0, 90.0, 90.0})
    p = K.compose(mv1, K.pose({63.5, 0.0, 0.0, 90.0, -90.0, 0.0}))
    assert close?(p.position, {650.0, -577.0, 1000.0})
    assert close?(p.rotation, {{-1.0, 0.0, 0.0}, {0.0, 1.0, 0.0}, {0.0, 0.0, -1.0}})
    assert close?(K.location(p), {650.0, -577.0, 1000.0, 0.0, 180.0, 0.0})
  end

  test "APPRO and DEPART offsets run along the tool Z axis" do
    down = K.pose({650.0, -450.0, 700.0, 0.0, 180.0, 0.0})
    assert close?(K.along_tool(down, -100).position, {650.0, -450.0, 800.0})
    sideways = K.pose({650.0, -513.5, 1000.0, 180.0, 90.0, 90.0})
    assert close?(K.along_tool(sideways, -50).position, {700.0, -513.5, 1000.0})
  end

  test "out of reach names the joint" do
    assert {:error, {2, _}} = K.joints(K.pose({800.0, 0.0, -800.0, 0.0, 180.0, 0.0}), @arm)
    assert {:error, {1, _}} = K.joints(K.pose({-800.0, 0.0, 1000.0, 0.0, 180.0, 0.0}), @arm)
    assert {:error, {3, _}} = K.joints(K.pose({3000.0, 0.0, 1000.0, 0.0, 180.0, 0.0}), @arm)
  end

  test "Euler angles at the A = 0 and A = 180 singularities give the same rotation back" do
    for {o, a, t} <- [
          {30.0, 0.0, 20.0},
          {30.0, 180.0, 20.0},
          {0.0, 180.0, 0.0},
          {-90.0, 0.0, 0.0}
        ] do
      r = K.euler(o, a, t)
      {o2, a2, t2} = K.to_euler(r)
      assert close?(K.euler(o2, a2, t2), r)
    end
  end

  defp angle, do: :proper_types.float(-179.0, 179.0)

  test "location(pose(l)) == l for A strictly between 0 and 180" do
    gen =
      {:proper_types.float(-2000.0, 2000.0), angle(), :proper_types.float(1.0, 179.0), angle()}

    assert_property(
      :proper.forall(gen, fn {x, o, a, t} ->
        l = {x, -x / 2, 500.0, o, a, t}
        close?(K.location(K.pose(l)), l, 1.0e-6)
      end),
      300
    )
  end

  test "joints and forward kinematics invert each other inside the envelope" do
    gen =
      {:proper_types.float(-150.0, 150.0), :proper_types.float(-45.0, 35.0),
       :proper_types.float(0.0, 900.0), angle(), :proper_types.float(1.0, 179.0), angle()}

    assert_property(
      :proper.forall(gen, fn {j1, j2, j3, j4, j5, j6} ->
        q = [j1, j2, j3, j4, j5, j6]
        pose = K.forward(q, @arm)
        {:ok, q2} = K.joints(pose, @arm)
        close?(q2, q, 1.0e-6) and pose_close?(K.forward(q2, @arm), pose)
      end),
      300
    )
  end

  test "angle differences wrap" do
    assert K.angle_difference(170.0, -170.0) == -20.0
    assert K.angle_difference(-170.0, 170.0) == 20.0
    assert K.angle_difference(10.0, 10.0) == 0.0
  end
end
