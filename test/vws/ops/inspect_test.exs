defmodule Vws.Ops.InspectTest do
  use ExUnit.Case, async: true

  import ExUnit.CaptureIO

  alias Vws.Ops.Inspect
  alias Vws.Test.WCPeer

  defmodule FakeLink do
    @moduledoc false
    # A device link as the equipment links are: a process under the links supervisor whose
    # module exports info/1.
    use Agent

    def start_link(info), do: Agent.start_link(fn -> info end)
    def info(pid), do: Agent.get(pid, & &1)
  end

  defmodule SilentLink do
    @moduledoc false
    use GenServer
    def start_link(_), do: GenServer.start_link(__MODULE__, nil)
    def init(nil), do: {:ok, nil}
    # never answers
    def info(pid), do: GenServer.call(pid, :info, :infinity)
    def handle_call(:info, _from, s), do: {:noreply, s}
  end

  defmodule RaisingLink do
    @moduledoc false
    # A link whose info/1 takes something other than its pid (as Vws.Links.HPIB's once did).
    use Agent
    def start_link(_), do: Agent.start_link(fn -> nil end)
    def info({_bus, _address}), do: %{}
  end

  setup do
    links = [
      Supervisor.child_spec(
        {FakeLink, %{state: :running, counters: %{frames_out: 12, naks: 1}, last_error: "NAK 2"}},
        id: :val_ii
      ),
      Supervisor.child_spec({SilentLink, nil}, id: :daq1)
    ]

    %{ws: ws, wc: wc} =
      Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot(), links: links)

    %{ws: ws, wc: wc}
  end

  test "partitions: state, current command, status, restarts", %{ws: ws, wc: wc} do
    {:ok, peer} = WCPeer.connect(wc)
    WCPeer.send_string(peer, 1, [{"R", 7, "HOLD X"}])
    assert_receive {:executing, cmd, 7, _}, 5_000

    robot = Enum.find(Inspect.partition_rows(ws), &(&1.partition == :robot))
    assert %{state: :running, number: 7, status: :executing, in_flight: 7, restarts: 0} = robot
    assert %{number: 7, text: "HOLD X"} = robot.current

    table = Inspect.format_partitions(ws)
    assert table =~ ~r/ROBOT +running +0007 EXECUTING +0007 HOLD X \(\d+ ms\)/
    assert table =~ ~r/MONARCH +idle +---- NONE/

    send(cmd, {:result, :done})

    assert Vws.Test.Eventually.eventually(fn ->
             Vws.CEC.Mailbox.command_status(ws, :robot) == {7, :done}
           end)

    # a partition that crashed and restarted says so
    Process.exit(Vws.CEC.Partition.whereis(ws, :monarch), :kill)

    assert Vws.Test.Eventually.eventually(fn ->
             match?(
               %{restarts: 1, state: :idle},
               Enum.find(Inspect.partition_rows(ws), &(&1.partition == :monarch))
             )
           end)
  end

  test "links: every child of the links supervisor, with its info/1 map; a silent one does not block",
       %{ws: ws} do
    {time, rows} = :timer.tc(fn -> Inspect.link_rows(ws) end)
    assert time < 2_000_000

    assert [%{id: :daq1, state: :not_answering}, %{id: :val_ii, state: :running, info: info}] =
             rows

    assert info.last_error == "NAK 2"

    table = Inspect.format_links(ws)

    assert table =~
             ~r/val_ii +#PID<[\d.]+> +running +counters: frames_out=12 naks=1  last_error=NAK 2/

    assert table =~ ~r/daq1 +#PID<[\d.]+> +not_answering/
  end

  test "interlocks: every lease, with its holder, reasons and age", %{ws: ws} do
    assert Inspect.format_interlocks(ws) =~ "(none held)"
    :ok = Vws.CEC.Interlock.acquire(ws, :table, :robot, 1_000)
    :ok = Vws.CEC.Interlock.acquire(ws, :tray2, :mhs, 1_000, as: :transfer)

    assert [
             %{what: :table, holder: :robot, reasons: [:lease]},
             %{what: :tray2, holder: :mhs, reasons: [:transfer], age_ms: age}
           ] = Inspect.interlock_rows(ws)

    assert is_integer(age)

    text = Inspect.format_interlocks(ws)
    assert text =~ ~r/^table +robot +lease +\d+ ms$/m
    assert text =~ ~r/^tray2 +mhs +transfer +\d+ ms$/m
  end

  test "a link whose info cannot be read is shown so, and every view still prints" do
    links = [
      Supervisor.child_spec({RaisingLink, nil}, id: :broken),
      Supervisor.child_spec({FakeLink, %{state: :ready}}, id: :fine)
    ]

    %{ws: ws} = Vws.Test.Workstation.start(links: links)

    assert [
             %{id: :broken, state: :unreadable, info: %{error: "** (FunctionClauseError)" <> _}},
             %{id: :fine, state: :ready}
           ] = Inspect.link_rows(ws)

    out = capture_io(fn -> Inspect.overview(ws) end)
    assert out =~ ~r/broken +#PID<[\d.]+> +unreadable +error=\*\* \(FunctionClauseError\)/
    assert out =~ ~r/fine +#PID<[\d.]+> +ready/
  end

  test "words: what a person reads, never an Elixir term" do
    assert Inspect.words({:ready, :still}) == "ready still"
    assert Inspect.words(:not_answering) == "not answering"
    assert Inspect.words(%{a: 1, b: [:x, "Y"]}) == "a 1, b x Y"
    assert Inspect.words(self()) == "process"
    assert Inspect.words(%Vws.Links.HPIB.Error{reason: :timeout, address: 9, detail: 500}) =~ "9"
    assert Inspect.words(nil) == "-"

    assert Vws.CEC.Mailbox.device_text({:no_data, "NO LINK TO DAQ #1"}) ==
             "NO DATA (NO LINK TO DAQ #1)"

    assert Vws.CEC.Mailbox.device_text(%Vws.Links.DAQ.Readings{
             seq: 3,
             values: %{vise_jaw_mm: 50.04}
           }) ==
             "POLL 3: VISE JAW WIDTH 50.0 MM"
  end

  test "the printed views", %{ws: ws} do
    out = capture_io(fn -> Inspect.overview(ws) end)
    assert out =~ "VWS mailboxes of workstation"
    assert out =~ "PARTITIONS of"
    assert out =~ "LINKS of"
    assert out =~ "INTERLOCKS of"
    assert out =~ "WC LINK of"
    assert capture_io(fn -> :ok = Inspect.partitions(ws) end) =~ "HYDRAULIC"
  end

  test "a partition that is down is shown down, not waited for", %{ws: ws} do
    sup = Vws.CEC.Workstation.whereis(ws, :partitions)
    :ok = Supervisor.terminate_child(sup, :vacuum)
    assert %{state: :down} = Enum.find(Inspect.partition_rows(ws), &(&1.partition == :vacuum))
  end

  test "watch a partition: its commands as they happen", %{ws: ws, wc: wc} do
    {:ok, peer} = WCPeer.connect(wc)
    {:ok, device} = StringIO.open("")
    watcher = Task.async(fn -> Inspect.watch(ws, :robot, timeout: 30_000, device: device) end)
    # the watcher subscribes before it waits; give it that moment through the telemetry table
    # it says so once it is subscribed
    assert Vws.Test.Eventually.eventually(fn ->
             StringIO.contents(device) |> elem(1) =~ "watching"
           end)

    WCPeer.send_string(peer, 1, [{"R", 7, "HOLD Y"}, {"G", 8, "OPEN"}])
    assert_receive {:executing, cmd, 7, _}, 5_000
    send(cmd, {:result, :done})

    assert Vws.Test.Eventually.eventually(
             fn -> StringIO.contents(device) |> elem(1) =~ "command_finished" end,
             10_000
           )

    send(watcher.pid, :stop_watch)
    printed = Task.await(watcher, 5_000)
    {_, out} = StringIO.contents(device)

    assert printed >= 3
    assert out =~ ~r/partition\.command_dispatched command=7 partition=robot text=HOLD Y/
    assert out =~ ~r/partition\.command\.stop command=7 partition=robot result=done/

    assert out =~
             ~r/partition\.command_finished command=7 partition=robot status=done duration=\d+ms/

    refute out =~ "partition=gripper"
  end

  # README: `watch("VWS", :robot)` shows ROBOT's traffic live — the VAL II messages, not only
  # the partition's own events (they were all it showed)
  test "watch the robot: the VAL II messages both ways" do
    sim = start_supervised!({Vws.Sim.VAL2, time_scale: 0.001}, id: :val2_sim)

    %{ws: ws, wc: wc} = Vws.Test.Workstation.start(devices: [robot: Vws.Sim.VAL2.endpoint(sim)])

    val = Vws.Names.via(ws, :val)
    assert Vws.Test.Eventually.eventually(fn -> Vws.Links.VAL.ready?(val) end, 10_000)
    {:ok, peer} = WCPeer.connect(wc)
    {:ok, device} = StringIO.open("")
    watcher = Task.async(fn -> Inspect.watch(ws, :robot, timeout: 30_000, device: device) end)

    # (attaching its handlers is a persistent_term update, which a full suite's thousands of
    # processes make slow)
    assert Vws.Test.Eventually.eventually(
             fn -> StringIO.contents(device) |> elem(1) =~ "watching" end,
             15_000
           )

    WCPeer.send_string(peer, 1, [{"R", 1, "WHERE"}])

    assert Vws.Test.Eventually.eventually(
             fn -> StringIO.contents(device) |> elem(1) =~ "command_finished" end,
             10_000
           )

    send(watcher.pid, :stop_watch)
    Task.await(watcher, 5_000)
    {_, out} = StringIO.contents(device)
    assert out =~ ~r/VAL II → LUN \d+ write: WHERE/
    assert out =~ ~r/VAL II ← LUN \d+ /
  end

  test "watch the WC: the dialogue both ways", %{ws: ws, wc: wc} do
    {:ok, peer} = WCPeer.connect(wc)
    {:ok, device} = StringIO.open("")
    watcher = Task.async(fn -> Inspect.watch(ws, :wc, timeout: 30_000, device: device) end)

    # it says so once it is subscribed
    assert Vws.Test.Eventually.eventually(fn ->
             StringIO.contents(device) |> elem(1) =~ "watching"
           end)

    WCPeer.send_string(peer, 3, [{"S", 9, "ROBOT_CMD"}])
    WCPeer.recv_line(peer)

    assert Vws.Test.Eventually.eventually(
             fn -> StringIO.contents(device) |> elem(1) =~ "NONE" end,
             10_000
           )

    send(watcher.pid, :stop_watch)
    Task.await(watcher, 5_000)
    {_, out} = StringIO.contents(device)
    assert out =~ ~r/\d\d:\d\d:\d\d\.\d{3} WC → \*0003\*S0009ROBOT_CMD\*\d{3}/
    assert out =~ ~r/WC ← \d\dS0009\d{4}NONE\d{3}/
  end
end
