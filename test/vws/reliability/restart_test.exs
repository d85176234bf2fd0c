defmodule Vws.Reliability.RestartTest do
  @moduledoc """
  Kill-and-restart (issue 8). The workstation dies in the middle of the shipped machining cycle
  (`priv/sims/machining_cycle.vws`, run by a WC through `Vws.Peers.WC.Runner`) — its supervisor on
  this node, or the whole `:peer` node it runs on — at a moment the simulated equipment itself
  picks: a robot motion begun, a part program half-way to the GE-2000, the vise CLOSE valve just
  energised. The equipment's counters are read while nothing of the workstation runs; then the
  workstation starts again with the same journal and the same endpoints, and:

    * every command status the WC asks for is the true one: DONE for what it saw DONE, `NONE`
      for a set it never used, and `ERROR INTERRUPTED BY RESTART` for the command in flight —
      never EXECUTING;
    * nothing physical ran again: the VAL II's monitor commands, the GE-2000's downloads and
      cycles and every relay write of the plant are what they were at the kill — also after the
      WC resends the acknowledged string byte for byte (acknowledged again, not run);
    * the work-volume leases are those of the moment of the kill, so a cycle start with the arm
      still in the vise is refused (`ERROR INTERLOCK TABLE HELD BY ROBOT`), and the plant's
      collision oracle records nothing.
  """
  use ExUnit.Case, async: true

  import Vws.Codecs.WC.Command, only: [pad4: 1]

  import Vws.Test.Eventually

  alias Vws.CEC.{Interlock, Mailbox, Workstation}
  alias Vws.Sim.{Floor, GE2000, Plant, VAL2}
  alias Vws.Test.WCPeer
  alias Vws.Peers.WC.{Client, ClientError, Runner, Script}
  alias Vws.Codecs.WC.CommandString

  @moduletag :tmp_dir
  # 8–11 s for the whole file here (2 shared cores): four cycles to their kill point (one on a
  # :peer node), two node starts
  @moduletag timeout: 120_000

  @scale 50
  @interrupted "ERROR INTERRUPTED BY RESTART"
  @letters ~w(R M G F V H)

  defmodule Trigger do
    @moduledoc false
    # Counts the equipment's events by key; at the armed key's nth occurrence it runs the kill
    # once, in the process that reported the event (a simulator's), and tells the test.

    def new(key, nth, action) do
      table = :ets.new(__MODULE__, [:public, :set])
      :ets.insert(table, {:armed, key, nth, action, self()})
      table
    end

    def event(table, key) do
      n = :ets.update_counter(table, {:count, key}, 1, {{:count, key}, 0})

      with [{:armed, ^key, ^n, action, test}] <- :ets.lookup(table, :armed),
           1 <- :ets.select_delete(table, [{{:armed, key, n, :_, :_}, [], [true]}]) do
        action.()
        send(test, {:killed, key})
      end

      :ok
    rescue
      # the test is over and its table gone: the floor is being stopped
      ArgumentError -> :ok
    end
  end

  ## The workstation supervisor killed

  @points [
    %{
      what: "a robot motion is under way (the arm moving into the vise to unload)",
      # the second DO MOVES VISE of the cycle: MOTION BEGIN, before MOTION COMPLETE
      trigger: {{:motion_begin, "VISE"}, 2},
      in_flight: {"R", "DO MOVES VISE"},
      leases: [%{volume: :table, holder: :robot, reasons: [:disabled, :inside]}],
      probe: "ERROR INTERLOCK TABLE HELD BY ROBOT"
    },
    %{
      what: "DOWNLOAD_GE is sending the part program (its first text block at the GE-2000)",
      trigger: {:ge_text_block, 1},
      in_flight: {"M", "DOWNLOAD_GE"},
      leases: [],
      probe: nil
    },
    %{
      what: "F CLOSE is being verified (the CLOSE valve just energised, the part in the gripper)",
      trigger: {{:relay, :vise_close_valve, true}, 1},
      in_flight: {"F", "CLOSE"},
      leases: [
        %{volume: :table, holder: :robot, reasons: [:disabled, :inside]},
        %{volume: :table, holder: :fixture, reasons: [:vise]}
      ],
      probe: "ERROR INTERLOCK TABLE HELD BY ROBOT"
    }
  ]

  for point <- @points do
    @point point
    test "workstation supervisor killed while #{point.what}", %{tmp_dir: dir} do
      point = @point
      ws = "restart-#{System.unique_integer([:positive])}"
      {key, nth} = point.trigger
      trigger = Trigger.new(key, nth, fn -> kill_workstation(ws) end)

      start_floor!(ws, trigger, mhs: true)
      if key == :ge_text_block, do: watch_ge_text_blocks(ws, trigger)

      gate = :ets.new(:gate, [:public, :set])
      old = start_supervised!(gated_workstation(ws_options(ws, dir), gate))
      on_this_node = &apply/3
      assert eventually(fn -> ready?(on_this_node, ws) end, 10_000)

      endpoint = "loopback:wc-#{ws}"
      cycle = start_cycle(endpoint)

      # the kill, and the equipment read while no part of the workstation runs
      assert_receive {:killed, ^key}, 30_000
      refute Process.alive?(old)
      at_kill = equipment(ws)
      in_progress!(key, ws)
      assert_stopped(cycle)

      # the test's supervisor starts it again with the same journal
      :ets.insert(gate, {:open, true})

      assert eventually(fn -> Workstation.whereis(ws) not in [nil, old] end, 10_000)
      assert eventually(fn -> ready?(on_this_node, ws) end, 10_000)

      assert Interlock.held(ws) |> Enum.map(&Map.take(&1, [:volume, :holder, :reasons])) ==
               point.leases

      after_restart(cycle, endpoint, point, ws, at_kill)
    end
  end

  ## A :peer node running the workstation, killed

  # The node is killed with SIGKILL on its OS process, not `:erlang.halt/2` by rpc: a halt is
  # code the node runs (it must be scheduled, it may flush ports when asked to), a SIGKILL is
  # what a crash or the OOM killer does — nothing of the node runs after it, no journal or socket
  # is closed in order. It is sent from the robot simulator at MOTION BEGIN, so the node dies
  # while the arm moves.
  test "a :peer node running the workstation killed (SIGKILL) while a robot motion is under way",
       %{tmp_dir: dir} do
    ws = "peer-restart-#{System.unique_integer([:positive])}"
    wc_port = free_port()
    endpoint = "tcp://127.0.0.1:#{wc_port}"
    nodes = :ets.new(:nodes, [:public, :set])

    trigger =
      Trigger.new({:motion_begin, "VISE"}, 2, fn ->
        [{:os_pid, os_pid}] = :ets.lookup(nodes, :os_pid)
        {_, 0} = System.cmd("kill", ["-KILL", os_pid])
      end)

    # the simulators here, so they outlive the node; the MHS takes its leases from the
    # workstation's own mailboxes, so it cannot sit on another node and is not started
    start_floor!(ws, trigger, mhs: false)
    opts = ws_options(ws, dir, wc: endpoint, devices: Floor.devices(ws))

    node = start_peer_workstation!(opts)
    :ets.insert(nodes, {:os_pid, node.os_pid})
    cycle = start_cycle(endpoint)

    assert_receive {:killed, {:motion_begin, "VISE"}}, 30_000
    peer = node.peer
    assert_receive {:DOWN, _, :process, ^peer, _}, 10_000
    at_kill = equipment(ws)
    in_progress!({:motion_begin, "VISE"}, ws)
    assert_stopped(cycle)

    # a new node, the same journal directory, the same endpoints
    node2 = start_peer_workstation!(opts)
    on_peer = fn m, f, a -> :peer.call(node2.peer, m, f, a, 10_000) end

    assert on_peer.(Interlock, :held, [ws])
           |> Enum.map(&Map.take(&1, [:volume, :holder, :reasons])) ==
             [%{volume: :table, holder: :robot, reasons: [:disabled, :inside]}]

    point = %{in_flight: {"R", "DO MOVES VISE"}, probe: "ERROR INTERLOCK TABLE HELD BY ROBOT"}
    after_restart(cycle, endpoint, point, ws, at_kill)
  end

  ## After the restart: what the WC asks, what it resends, what it tries

  defp after_restart(cycle, endpoint, point, ws, at_kill) do
    %{client: client} = cycle
    record = wc_record(cycle)

    # the command in flight is the one the equipment was doing, its string acknowledged
    {letter, text} = point.in_flight
    assert %{letter: ^letter, text: ^text, number: in_flight} = record.in_flight
    assert record.in_flight_acked

    # every command status the WC asks for is the true one
    for letter <- @letters do
      name = Client.command_status_name(letter)
      assert {:ok, answer} = Client.status(client, name)

      expected =
        case Map.fetch(record.last, letter) do
          :error ->
            "0000NONE"

          {:ok, n} when letter == point.in_flight |> elem(0) and n == in_flight ->
            "#{pad4(n)}#{@interrupted}"

          {:ok, n} ->
            assert {letter, n} in record.done, "#{name}: the WC never saw #{pad4(n)} DONE"
            "#{pad4(n)}DONE"
        end

      assert answer == expected, "#{name}"
    end

    # an interrupted vise motion's safe clean-up ran: both valves off (issue 15)
    if letter == "F" do
      assert eventually(fn ->
               relays = Plant.snapshot(Floor.plant(ws)).relays
               {:daq1, 205} not in relays and {:daq1, 206} not in relays
             end)
    end

    # nothing re-ran by itself, and the acknowledged string resent byte for byte is
    # acknowledged again and not run
    assert same_work?(equipment(ws), at_kill)
    {:ok, peer} = WCPeer.connect(endpoint)
    :ok = WCPeer.send_raw(peer, record.last_line <> "\r\n")
    assert WCPeer.recv_line(peer) =~ ~r/^05A#{pad4(record.last_seq)}/

    in_flight_status = Client.command_status_name(letter)

    assert WCPeer.status(peer, rem(record.last_seq + 1, 10_000), 1, in_flight_status) ==
             "#{pad4(in_flight)}#{@interrupted}"

    WCPeer.close(peer)
    assert same_work?(equipment(ws), at_kill)

    # that connection took the link over from the WC client's (takeover_after: 0): the client
    # has seen its link closed before it is asked again, and opens it anew for the next string
    # (asked at once, it could still send on the closed link and end with :closed)
    assert eventually(fn -> Client.info(client).peer == nil end, 10_000)

    # a cycle start with the arm still where the interrupted motion left it: refused by the
    # leases the journal kept, and nothing moves
    if point.probe do
      sent = Client.send_commands(client, [{"M", "CYCLE_START"}])

      assert match?({:ok, [{"M", _}]}, sent),
             "CYCLE_START: #{inspect(sent)}; the client's last events:\n" <>
               Enum.map_join(Enum.take(Client.log(client), -20), "\n", &inspect/1)

      {:ok, [{"M", n}]} = sent

      assert {:error, %ClientError{reason: :command_failed, data: %{status: status}}} =
               Client.await_command(client, "M", n, 15_000, poll_interval: 5)

      assert status == point.probe
      assert same_work?(equipment(ws), at_kill)
    end

    assert Plant.collisions(Floor.plant(ws)) == []
  end

  ## The floor, the workstation, the WC

  defp start_floor!(ws, trigger, opts) do
    plant = Floor.plant(ws)

    start_supervised!(
      {Floor,
       workstation: ws,
       time_scale: @scale,
       seed: 7,
       hydraulic: {Vws.Peers.HydraulicController, []},
       ge2000: true,
       mhs: Keyword.fetch!(opts, :mhs),
       robot: [
         on_move: fn
           %{phase: :begin} = move ->
             Plant.set_robot(plant, %{volume: move.volume})
             Trigger.event(trigger, {:motion_begin, move.location})

           move ->
             Plant.set_robot(plant, %{volume: move.volume})
         end
       ],
       on_relay: fn signal, on? -> Trigger.event(trigger, {:relay, signal, on?}) end}
    )

    :ok = Vws.Peers.HydraulicController.await_ready(Floor.hydraulic_controller(ws), 10_000)
    :ok = Plant.set_part(plant, :tray1, true)
  end

  # The GE-2000's DNC link tells of each block it accepts; block 1 of a transmission is the
  # command, the blocks after it its text: only a download from the CEC has any.
  defp watch_ge_text_blocks(ws, trigger) do
    link = GE2000.link(Floor.ge2000(ws))
    id = {__MODULE__, ws}

    :ok =
      Vws.Telemetry.attach(
        id,
        [:vws, :dnc, :block_received],
        fn _event, _measurements, meta, {link, trigger} ->
          if self() == link and meta.block >= 2, do: Trigger.event(trigger, :ge_text_block)
        end,
        {link, trigger}
      )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
  end

  defp ws_options(ws, dir, extra \\ []) do
    [
      id: ws,
      wc: "loopback:wc-#{ws}",
      # the check after a restart sends from a second WC while the first has just spoken: it
      # may take the link over at once (by default only after 10 s of the first one's silence)
      sun_comm: [takeover_after: 0],
      journal: [dir: dir],
      devices: Floor.devices(ws),
      # a refused cycle start ends in half a second, not ten
      partitions: [monarch: [options: [start_timeout: 2_000, interlock: [timeout: 500]]]]
    ]
    |> Keyword.merge(extra)
  end

  # Process.exit(supervisor, :kill), and the equipment waits until every process of the
  # workstation's tree is dead: a device's next step (the GE-2000's acknowledgement of a block)
  # must not reach a part of the workstation still going down, or the kill is not where it
  # was meant to be.
  defp kill_workstation(ws) do
    sup = Workstation.whereis(ws)
    refs = sup |> tree() |> Enum.map(&Process.monitor/1)
    Process.exit(sup, :kill)

    for ref <- refs do
      receive do
        {:DOWN, ^ref, :process, _, _} -> :ok
      after
        5_000 -> raise "the workstation did not die"
      end
    end
  end

  defp tree(sup) do
    [
      sup
      | for {_id, pid, type, _} <- Supervisor.which_children(sup), is_pid(pid) do
          if type == :supervisor, do: tree(pid), else: [pid]
        end
    ]
    |> List.flatten()
  end

  # `Vws.CEC.Workstation`'s child spec, except that a restart waits until the test opens the gate:
  # the test reads the equipment between the death and the restart.
  defp gated_workstation(opts, gate) do
    %{Workstation.child_spec(opts) | start: {__MODULE__, :start_gated, [opts, gate]}}
  end

  @doc false
  def start_gated(opts, gate) do
    if :ets.update_counter(gate, :starts, 1, {:starts, 0}) > 1, do: await_gate(gate)
    Workstation.start_link(opts)
  rescue
    # the test is over: its gate is gone
    ArgumentError -> :ignore
  end

  defp await_gate(gate) do
    if :ets.lookup(gate, :open) == [], do: Process.sleep(5) && await_gate(gate)
  end

  # Up and reading its equipment: the VAL II link ready, the GE-2000 read IDLE, DAQ #1 read.
  defp ready?(call, ws) do
    val = call.(Workstation, :whereis, [ws, :val])

    val != nil and call.(Vws.Links.VAL, :ready?, [val]) and
      match?({"IDLE", _}, call.(Mailbox, :get_device, [ws, 8])) and
      match?({:ok, _}, call.(Vws.Partitions.VwsStatus, :readings, [ws])) and
      call.(Vws.CEC.SunComm, :listening, [ws]) != nil
  catch
    _kind, _reason -> false
  end

  defp start_cycle(endpoint) do
    {:ok, script} = Script.parse_file("priv/sims/machining_cycle.vws")
    log = spawn_link(fn -> collect([]) end)
    {:ok, client} = Client.connect(endpoint, subscribe: log, connect_timeout: 10_000)
    task = Task.async(fn -> Runner.run(client, script, poll_interval: 5) end)
    %{client: client, log: log, task: task}
  end

  # The link died under the runner and nothing answers until the workstation is back: it stops.
  defp assert_stopped(%{task: task}) do
    summary = Task.await(task, 30_000)
    assert summary.result == :stopped
  end

  defp collect(events) do
    receive do
      {:wc_client, _client, event} ->
        collect([event | events])

      {:events, from} ->
        send(from, {:events, self(), Enum.reverse(events)})
        collect(events)
    end
  end

  # What the WC sent and saw before the kill: per set the last command number it sent, the
  # commands it saw DONE, and its last command string (the one in flight).
  defp wc_record(%{log: log}) do
    send(log, {:events, self()})
    assert_receive {:events, ^log, events}

    strings =
      for %{direction: :sent, kind: :string, line: line} <- events do
        {:ok, cs} = CommandString.decode(line)
        {line, cs}
      end

    {last_line, last} = List.last(strings)

    last_numbers =
      for {_line, cs} <- strings, c <- cs.commands, into: %{}, do: {c.letter, c.number}

    done =
      for %{direction: :received, kind: :status, meaning: meaning} <- events,
          [_, set, n] <- [Regex.run(~r/^(\w+) (\d{4}) DONE$/, meaning)],
          letter <- @letters,
          Client.command_status_name(letter) == set <> "_CMD",
          into: MapSet.new(),
          do: {letter, String.to_integer(n)}

    [command] = last.commands

    %{
      last: last_numbers,
      done: done,
      last_line: last_line,
      last_seq: last.sequence,
      in_flight: %{letter: command.letter, text: command.text, number: command.number},
      in_flight_acked:
        Enum.any?(events, fn e ->
          e.direction == :received and e.kind == :ack and
            String.starts_with?(e.line, "05A" <> pad4(last.sequence))
        end)
    }
  end

  ## The equipment

  # What the equipment was made to do: the VAL II's monitor commands, the GE-2000's downloads
  # and cycles, every relay write of the plant (both DAQs, so the hydraulic controller's too).
  defp equipment(ws) do
    ge = GE2000.state(Floor.ge2000(ws))

    %{
      robot_commands: VAL2.info(Floor.robot(ws)).commands,
      ge_downloads: ge.downloads,
      ge_cycles: ge.cycles,
      ge_directory: ge.directory,
      relay_writes: Plant.writes(Floor.plant(ws))
    }
  end

  # Nothing was done again: the same writes, except that a restarted VWS_STATUS lets go of every
  # push button (the cycle-start relay, already open) and an interrupted vise motion's clean-up
  # turns both vise valves off (issue 15) — the safe state, never a press or a valve energised.
  defp same_work?(now, at_kill) do
    safe = [{:daq1, 210}, {:daq1, 205}, {:daq1, 206}]
    closes = fn w, relay -> Map.get(w, relay, %{close: 0}).close end
    drop = &Map.update!(&1, :relay_writes, fn w -> Map.drop(w, safe) end)

    Enum.all?(safe, &(closes.(now.relay_writes, &1) == closes.(at_kill.relay_writes, &1))) and
      drop.(now) == drop.(at_kill)
  end

  # The kill came while the equipment was doing the command.
  defp in_progress!({:motion_begin, "VISE"}, ws) do
    assert [last_command | _] = Enum.reverse(VAL2.info(Floor.robot(ws)).commands)
    assert last_command == "DO MOVES VISE"
  end

  defp in_progress!(:ge_text_block, ws) do
    # half a program is not a program: the GE-2000 filed nothing
    assert %{downloads: 0, directory: []} = GE2000.state(Floor.ge2000(ws))
  end

  defp in_progress!({:relay, :vise_close_valve, true}, ws) do
    assert {:daq1, 206} in Plant.snapshot(Floor.plant(ws)).relays
  end

  ## The peer node

  defp start_peer_workstation!(opts) do
    paths = Enum.flat_map(:code.get_path(), &[~c"-pa", &1])

    {:ok, peer, _node} =
      :peer.start(%{
        connection: :standard_io,
        name: :peer.random_name(~c"vws_restart"),
        args: paths ++ [~c"-logger", ~c"level", ~c"error"]
      })

    Process.monitor(peer)

    on_exit(fn ->
      try do
        :peer.stop(peer)
      catch
        :exit, _ -> :already_gone
      end
    end)

    os_pid = to_string(:peer.call(peer, :os, :getpid, []))
    {:ok, _} = :peer.call(peer, Application, :ensure_all_started, [:vws], 30_000)
    :ok = :peer.call(peer, Logger, :configure, [[level: :error]])
    {:ok, _} = :peer.call(peer, Workstation, :start, [opts], 30_000)
    on_peer = fn m, f, a -> :peer.call(peer, m, f, a, 10_000) end
    assert eventually(fn -> ready?(on_peer, Keyword.fetch!(opts, :id)) end, 15_000)
    %{peer: peer, os_pid: os_pid}
  end

  defp free_port do
    {:ok, socket} = :gen_tcp.listen(0, ip: {127, 0, 0, 1}, reuseaddr: true)
    {:ok, port} = :inet.port(socket)
    :ok = :gen_tcp.close(socket)
    port
  end
end
