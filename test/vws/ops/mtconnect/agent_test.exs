defmodule Vws.Ops.MTConnect.AgentTest do
  use ExUnit.Case, async: true

  # validates against the official schemas (test/test_helper.exs excludes it without them)
  @moduletag :mtconnect_schemas

  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.Ops.MTConnect.Agent
  alias Vws.Test.XMLLint

  # The agent serves only this test's workstations (others run concurrently).
  defp agent(ids, opts \\ []) do
    start_supervised!(
      {Agent, [workstations: fn -> ids end, interval: 60_000] ++ opts},
      id: make_ref()
    )
  end

  # {element, dataItemId, sequence, value} of every observation in a streams document
  defp observations(text) do
    ~r{<(\w+) dataItemId="([^"]+)" timestamp="[^"]+" sequence="(\d+)"[^>]*>([^<]*)</\1>}
    |> Regex.scan(text, capture: :all_but_first)
    |> Enum.map(fn [el, id, seq, value] -> {el, id, String.to_integer(seq), value} end)
  end

  defp value(text, id) do
    case for({_, ^id, _, v} <- observations(text), do: v) do
      [] -> nil
      values -> List.last(values)
    end
  end

  defp header(text, attr) do
    [_, n] = Regex.run(~r{<Header [^>]*#{attr}="(\d+)"}, text)
    String.to_integer(n)
  end

  defp current!(agent, device \\ nil) do
    {:ok, xml} = Agent.current(agent, device)
    XMLLint.validate!(xml, :streams)
  end

  setup do
    %{ws: ws} = Vws.Test.Workstation.start()
    %{ws: ws, id: "ws_" <> ws}
  end

  test "probe: one device per workstation, named by its id; it validates", %{ws: ws} do
    %{ws: other} = Vws.Test.Workstation.start()
    a = agent([ws, other])
    {:ok, xml} = Agent.probe(a)
    text = XMLLint.validate!(xml, :devices)
    assert text =~ ~s(<Device id="ws_#{ws}" name="#{ws}")
    assert text =~ ~s(<Device id="ws_#{other}" name="#{other}")
    assert text =~ ~s(<Controller id="ws_#{ws}_vmc" name="vmc">)
    assert text =~ ~s(<Chuck id="ws_#{ws}_vise" name="vise">)
    {:ok, one} = Agent.probe(a, ws)
    refute XMLLint.validate!(one, :devices) =~ other
  end

  test "current shows what the mailboxes say now", %{ws: ws, id: id} do
    a = agent([ws])
    text = current!(a)
    assert value(text, "#{id}_avail") == "AVAILABLE"
    assert value(text, "#{id}_vmc_avail") == "UNAVAILABLE"
    assert value(text, "#{id}_vise_msg") == "NO DATA (NO LINK TO DAQ #1)"

    Mailbox.put_device(ws, 3, "VISE JAWS ARE 75 MM APART AND VISE IS LOCKED PART IN VISE")
    Mailbox.put_device(ws, 4, "TRAY #1 IN POSITION TRAY #2 NOT IN POSITION")
    Mailbox.put_device(ws, 8, "ACTIVE")
    Mailbox.put_device(ws, 9, "350/0/-20/90/0/0/1/2/3/4/5/6")
    Mailbox.put_device(ws, 10, "PALLET CLAMPED")
    Mailbox.put_device(ws, 1, "GRIPPER IS OPEN AND INDEXER ROTATED 90 DEG")
    :ok = Mailbox.dispatch(ws, :monarch, 5, "PROGRAM_SELECT(000777)")
    :ok = Mailbox.dispatch(ws, :robot, 6, "DO MOVE TRAY1")

    text = current!(a)
    assert value(text, "#{id}_vise_state") == "CLOSED"
    assert value(text, "#{id}_vise_part") == "PRESENT"
    assert value(text, "#{id}_tray1_state") == "LOCKED"
    assert value(text, "#{id}_tray2_state") == "UNLOCKED"
    assert value(text, "#{id}_vmc_avail") == "AVAILABLE"
    assert value(text, "#{id}_vmc_mode") == "AUTOMATIC"
    assert value(text, "#{id}_vmc_path_exec") == "ACTIVE"
    assert value(text, "#{id}_vmc_path_program") == "000777"
    assert value(text, "#{id}_robot_path_exec") == "ACTIVE"
    assert value(text, "#{id}_robot_path_pos") == "350 0 -20"
    assert value(text, "#{id}_pallet_state") == "LOCKED"
    assert value(text, "#{id}_gripper_state") == "OPEN"

    # each data item appears once in current, with its latest sequence number
    ids = for {_, i, _, _} <- observations(text), do: i
    assert ids == Enum.uniq(ids)
  end

  test "sample: sequence numbers in order from `from`, at most `count`, nextSequence after them",
       %{ws: ws, id: id} do
    a = agent([ws])
    %{first: 1, next: next} = Agent.sequences(a)
    Mailbox.put_device(ws, 10, "PALLET CLAMPED")
    Mailbox.put_device(ws, 10, "PALLET NOT CLAMPED")

    {:ok, xml} = Agent.sample(a, 1, 5)
    text = XMLLint.validate!(xml, :streams)
    assert Enum.map(observations(text), &elem(&1, 2)) |> Enum.sort() == [1, 2, 3, 4, 5]
    assert header(text, "nextSequence") == 6
    assert header(text, "firstSequence") == 1

    # both pallet changes are recorded, in order, though no one asked between them: the
    # agent records each change when it is announced (it sampled every 250 ms before, and the
    # second write hid the first)
    {:ok, xml} = Agent.sample(a, next, 100)
    text = XMLLint.validate!(xml, :streams)

    for item <- ["#{id}_pallet_state", "#{id}_pallet_msg"] do
      assert for({_, ^item, _, v} <- observations(text), do: v) ==
               if(item =~ "state",
                 do: ["LOCKED", "UNLOCKED"],
                 else: ["PALLET CLAMPED", "PALLET NOT CLAMPED"]
               )
    end

    # from = nextSequence: nothing yet, and that is not an error
    %{next: next} = Agent.sequences(a)
    {:ok, xml} = Agent.sample(a, next, 10)
    text = XMLLint.validate!(xml, :streams)
    assert observations(text) == []
    assert header(text, "nextSequence") == next
  end

  test "every transition is recorded when it happens: 25 robot commands, 25 ACTIVE records",
       %{ws: ws, id: id} do
    a = agent([ws])
    %{next: next} = Agent.sequences(a)

    # no one asks the agent in between (its periodic read is a minute away)
    for n <- 1..25 do
      :ok = Mailbox.dispatch(ws, :robot, n, "DO MOVE TRAY1")
      :ok = Mailbox.finish(ws, :robot, n, :done)
    end

    {:ok, xml} = Agent.sample(a, next, 1000)
    text = XMLLint.validate!(xml, :streams)
    exec = for {_, i, _, v} <- observations(text), i == "#{id}_robot_path_exec", do: v
    assert Enum.count(exec, &(&1 == "ACTIVE")) == 25
    assert Enum.count(exec, &(&1 == "READY")) == 25
    assert Enum.dedup(exec) == exec

    # in order: each message names its command
    msgs = for {_, i, _, v} <- observations(text), i == "#{id}_robot_msg", do: v
    assert hd(msgs) == "0001 DO MOVE TRAY1 EXECUTING"
    assert List.last(msgs) == "0025 DO MOVE TRAY1 DONE"
  end

  test "a circular buffer: old observations fall out, and asking for them is OUT_OF_RANGE",
       %{ws: ws} do
    a = agent([ws], buffer_size: 25)

    for i <- 1..20 do
      Mailbox.put_device(
        ws,
        10,
        if(rem(i, 2) == 0, do: "PALLET CLAMPED", else: "PALLET NOT CLAMPED")
      )

      Agent.sequences(a)
    end

    %{first: first, last: last, next: next, size: 25} = Agent.sequences(a)
    assert last - first + 1 == 25
    assert first > 1

    {:error, 400, xml} = Agent.sample(a, first - 1, 10)
    assert XMLLint.validate!(xml, :error) =~ ~s(errorCode="OUT_OF_RANGE")

    {:error, 400, xml} = Agent.sample(a, next + 1, 10)
    assert XMLLint.validate!(xml, :error) =~ ~s(errorCode="OUT_OF_RANGE")

    {:error, 400, xml} = Agent.sample(a, first, 0)
    assert XMLLint.validate!(xml, :error) =~ "&apos;count&apos; must not be zero(0)"

    {:error, 400, xml} = Agent.sample(a, first, 26)
    assert XMLLint.validate!(xml, :error) =~ "&apos;count&apos; must be between -25 and 25"
    {:error, 400, _} = Agent.sample(a, first, -26)

    {:ok, xml} = Agent.sample(a, first, 25)
    text = XMLLint.validate!(xml, :streams)
    assert Enum.map(observations(text), &elem(&1, 2)) |> Enum.sort() == Enum.to_list(first..last)
    assert header(text, "firstSequence") == first
    assert header(text, "nextSequence") == next
  end

  test "an unknown device is NO_DEVICE", %{ws: ws} do
    a = agent([ws])
    {:error, 404, xml} = Agent.current(a, "NOPE")
    assert XMLLint.validate!(xml, :error) =~ ~s(errorCode="NO_DEVICE")
    {:error, 404, _} = Agent.sample(a, nil, nil, "NOPE")
  end

  test "a stopped workstation's items become UNAVAILABLE; it stays in the probe; it comes back",
       %{id: id} do
    ws = "agent-stop-#{System.unique_integer([:positive])}"
    {:ok, _} = Workstation.start(id: ws, wc: nil)
    a = agent([ws])
    Mailbox.put_device(ws, 10, "PALLET CLAMPED")
    %{next: next} = Agent.sequences(a)
    assert id != "ws_" <> ws

    :ok = Workstation.stop(ws)
    # the registry forgets a stopped workstation's names a moment after it stopped
    assert Vws.Test.Eventually.eventually(fn ->
             not Mailbox.exists?(ws) and Workstation.whereis(ws) == nil
           end)

    {:ok, xml} = Agent.sample(a, next, 100)

    values =
      for {_, i, _, v} <- observations(XMLLint.validate!(xml, :streams)), into: %{}, do: {i, v}

    assert values["ws_#{ws}_avail"] == "UNAVAILABLE"
    assert values["ws_#{ws}_pallet_state"] == "UNAVAILABLE"

    {:ok, probe} = Agent.probe(a)
    assert XMLLint.validate!(probe, :devices) =~ ~s(<Device id="ws_#{ws}")
    assert values["agent_device_removed"] == "vws-#{ws}"

    {:ok, _} = Workstation.start(id: ws, wc: nil)
    on_exit(fn -> Workstation.stop(ws) end)
    text = current!(a)
    assert value(text, "ws_#{ws}_avail") == "AVAILABLE"
    assert value(text, "agent_device_added") == "vws-#{ws}"
  end

  test "before any workstation has run, the probe is a NO_DEVICE error" do
    a = agent([])
    {:error, 404, xml} = Agent.probe(a)
    assert XMLLint.validate!(xml, :error) =~ "no workstation has run yet"
    {:ok, xml} = Agent.current(a)
    assert value(XMLLint.validate!(xml, :streams), "agent_avail") == "AVAILABLE"
  end
end
