defmodule Vws.Ops.MTConnect.FloorAgentTest do
  # The agent on the demo's simulated shop floor, through a whole machining cycle: what a cell
  # operator watches is there, with units and without noise; the robot's message follows its
  # commands (it read "NO DATA (NO LINK TO VAL II)" while the robot worked).
  use ExUnit.Case, async: true

  # validates against the official schemas (test/test_helper.exs excludes it without them)
  @moduletag :mtconnect_schemas

  alias Vws.Ops.MTConnect.Agent
  alias Vws.Test.{MTCClient, XMLLint}
  alias Vws.Peers.WC.{Client, Runner, Script}

  @moduletag timeout: 120_000

  # The demo's shop floor (time scale ×50) and an agent that serves it alone. The agent never
  # reads on its own (its periodic read is a minute away): every change is told.
  defp floor_and_agent(prefix) do
    ws = "#{prefix}-#{System.unique_integer([:positive])}"
    on_exit(fn -> Vws.CEC.Workstation.stop(ws) end)
    {:ok, floor} = Vws.Ops.Demo.start_shop_floor(id: ws, wc: "loopback:#{ws}", time_scale: 50.0)
    a = start_supervised!({Agent, workstations: fn -> [ws] end, interval: 60_000}, id: make_ref())
    %{ws: ws, id: "ws_" <> ws, floor: floor, agent: a}
  end

  test "a machining cycle: robot messages, program, part count, samples, conditions, links" do
    %{ws: ws, id: id, floor: floor, agent: a} = floor_and_agent("floor-mtc")

    %{next: start} = Agent.sequences(a)

    {:ok, script} = Script.parse_file(Vws.Ops.Demo.default_script())
    {:ok, client} = Client.connect(floor.wc)
    summary = Runner.run(client, script, poll_interval: 5)
    assert summary.result == :completed, inspect(summary, limit: 20)

    # the robot's location: the cycle asks WHERE at SAFE (twice), so WHERE_ROBOT holds numbers
    {where, _age} = Vws.CEC.Mailbox.get_device(ws, 9)
    assert length(String.split(where, "/")) == 12, where
    assert Enum.all?(String.split(where, "/"), &(&1 =~ ~r/^-?\d+\.\d$/)), where

    {:ok, xml} = Agent.sample(a, start, 100_000)
    text = XMLLint.validate!(xml, :streams)
    obs = MTCClient.observations(text)
    values = fn item -> for {_, ^item, _, v} <- obs, do: v end

    robot_commands =
      for(%{op: {:commands, cmds}} <- script.steps, {"R", _} <- cmds, do: 1) |> length()

    assert robot_commands > 10
    msgs = values.("#{id}_robot_msg")
    refute Enum.any?(msgs, &(&1 =~ "NO DATA")), inspect(msgs)
    assert Enum.count(msgs, &(&1 =~ ~r/^\d{4} .+ DONE$/)) == robot_commands
    assert Enum.count(msgs, &(&1 =~ ~r/^\d{4} .+ EXECUTING$/)) == robot_commands
    assert Enum.count(values.("#{id}_robot_path_exec"), &(&1 == "ACTIVE")) == robot_commands

    # the VMC: its program from the GE-2000's own report, one part made, no fault
    {:ok, xml} = Agent.current(a)
    now = XMLLint.validate!(xml, :streams)

    current = fn item ->
      for({_, ^item, _, v} <- MTCClient.observations(now), do: v) |> List.last()
    end

    # ... and the agent shows the arm's position and joint angles from it
    assert current.("#{id}_robot_x_pos") =~ ~r/^-?\d+(\.\d+)?$/
    assert current.("#{id}_robot_j1_angle") =~ ~r/^-?\d+(\.\d+)?$/
    assert current.("#{id}_vmc_path_program") =~ ~r/^\d+$/
    assert current.("#{id}_vmc_path_part_count") == "1"
    # the cycle's DOWNLOAD_GE, block by block, as the VMC's transfer message (the link's progress)
    transfers = values.("#{id}_vmc_path_transfer")

    assert Enum.any?(transfers, &(&1 =~ ~r/^SENDING (\d{6}\.PRO|NC FILE) \d+\/\d+ BYTES/)),
           inspect(transfers)

    assert current.("#{id}_vmc_path_transfer") =~ ~r/^(SENT|RECEIVED) (\d{6}\.PRO|NC FILE) \d+/
    assert now =~ ~r/<Normal dataItemId="#{id}_vmc_system"/
    assert now =~ ~r/<Normal dataItemId="#{id}_robot_system"/

    # numeric samples with their units; the vise jaw moved during the cycle, in few records
    {:ok, probe} = Agent.probe(a)
    probe = XMLLint.validate!(probe, :devices)

    assert probe =~
             ~s(<DataItem id="#{id}_vise_jaw" type="LENGTH" category="SAMPLE" name="jaw_width" units="MILLIMETER">)

    assert probe =~ ~s(<Filter type="MINIMUM_DELTA">0.5</Filter>)

    assert probe =~
             ~s(id="#{id}_pallet_force1" type="LINEAR_FORCE" category="SAMPLE" name="clamp1_force" units="NEWTON")

    jaw = for v <- values.("#{id}_vise_jaw"), {f, ""} <- [Float.parse(v)], do: f
    assert length(jaw) >= 2
    assert Enum.max(jaw) - Enum.min(jaw) > 10
    forces = for v <- values.("#{id}_pallet_force1"), {f, ""} <- [Float.parse(v)], do: f
    assert Enum.max(forces) >= 4000, "the pallet was clamped during the cycle"

    # consecutive jaw records differ by at least the deadband (noise is not recorded); a record
    # after UNAVAILABLE (DAQ #1 not answering on a loaded machine) starts afresh
    jaw_records = for v <- values.("#{id}_vise_jaw"), do: Float.parse(v)

    for [{x, ""}, {y, ""}] <- Enum.chunk_every(jaw_records, 2, 1, :discard),
        do: assert(abs(x - y) >= 0.5)

    # the vise's message is recorded when its words change or its numbers move by 0.5 or more:
    # never for the ±0.1 mm of sensor noise (it changed ~3 times a second from noise before)
    vise = values.("#{id}_vise_msg")

    for [x, y] <- Enum.chunk_every(vise, 2, 1, :discard) do
      nx = for [n] <- Regex.scan(~r/\d+\.\d+/, x), do: String.to_float(n)
      ny = for [n] <- Regex.scan(~r/\d+\.\d+/, y), do: String.to_float(n)
      words = &String.replace(&1, ~r/\d+(\.\d+)?/, "#")

      assert words.(x) != words.(y) or
               Enum.any?(Enum.zip(nx, ny), fn {a, b} -> abs(a - b) >= 0.5 end),
             "#{x} -> #{y}"
    end

    # the links, as components
    for link <- ~w(val dnc daq1 hydraulic) do
      assert current.("#{id}_#{link}_link_conn") == "ESTABLISHED", link
    end

    assert current.("#{id}_wc_link_conn") == "ESTABLISHED"
  end

  test "each link's connection is recorded when it changes: a WC that comes and goes, links killed" do
    %{id: id, ws: ws, floor: floor, agent: a} = floor_and_agent("floor-links")

    conn = fn link ->
      {:ok, xml} = Agent.current(a)

      obs = MTCClient.observations(IO.iodata_to_binary(xml))
      for({_, item, _, v} <- obs, item == "#{id}_#{link}_link_conn", do: v) |> List.last()
    end

    for link <- ~w(val dnc daq1 hydraulic) do
      assert Vws.Test.Eventually.eventually(fn -> conn.(link) == "ESTABLISHED" end, 10_000), link
    end

    assert conn.("wc") == "LISTEN"
    %{next: start} = Agent.sequences(a)

    # a WC comes and goes, twice
    for _ <- 1..2 do
      {:ok, client} = Client.connect(floor.wc)
      assert Vws.Test.Eventually.eventually(fn -> conn.("wc") == "ESTABLISHED" end)
      Client.close(client)
      assert Vws.Test.Eventually.eventually(fn -> conn.("wc") == "LISTEN" end)
    end

    # the GE-2000's and the robot's link processes killed: closed, then up again on their own
    for key <- [:ge2000, :val] do
      pid = Vws.CEC.Workstation.whereis(ws, key)
      ref = Process.monitor(pid)
      Process.exit(pid, :kill)
      assert_receive {:DOWN, ^ref, _, _, _}
    end

    for link <- ~w(dnc val) do
      assert Vws.Test.Eventually.eventually(fn -> conn.(link) == "ESTABLISHED" end, 10_000), link
    end

    {:ok, xml} = Agent.sample(a, start, 1000)
    obs = MTCClient.observations(XMLLint.validate!(xml, :streams))
    values = fn link -> for {_, item, _, v} <- obs, item == "#{id}_#{link}_link_conn", do: v end

    assert values.("wc") == ~w(ESTABLISHED LISTEN ESTABLISHED LISTEN)
    assert values.("dnc") == ~w(CLOSED ESTABLISHED)
    assert values.("val") == ~w(CLOSED ESTABLISHED)
  end

  test "a command that ends ERROR is a Fault condition with its native code, then Normal again" do
    %{ws: ws} = Vws.Test.Workstation.start()
    a = start_supervised!({Agent, workstations: fn -> [ws] end, interval: 60_000}, id: make_ref())
    Vws.CEC.Mailbox.put_device(ws, 1, "GRIPPER IS OPEN AND INDEXER ROTATED 0 DEG")

    Vws.CEC.Mailbox.put_device(ws, 11, %Vws.Links.DAQ.Readings{values: %{gripper_finger_mm: 80.0}})

    %{next: next} = Agent.sequences(a)

    :ok = Vws.CEC.Mailbox.dispatch(ws, :gripper, 4, "CLOSE")
    :ok = Vws.CEC.Mailbox.finish(ws, :gripper, 4, {:error, "GRIPPER DID NOT CLOSE"})
    :ok = Vws.CEC.Mailbox.dispatch(ws, :gripper, 5, "OPEN")
    :ok = Vws.CEC.Mailbox.finish(ws, :gripper, 5, :done)

    {:ok, xml} = Agent.sample(a, next, 100)
    text = XMLLint.validate!(xml, :streams)

    assert text =~
             ~r{<Fault dataItemId="ws_#{ws}_gripper_system"[^>]* type="SYSTEM" nativeCode="CEC" conditionId="CEC">0004 ERROR GRIPPER DID NOT CLOSE</Fault>}

    assert text =~ ~r{<Normal dataItemId="ws_#{ws}_gripper_system"[^>]*/>}
  end
end
