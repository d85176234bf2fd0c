defmodule Vws.Reliability.ReconnectTest do
  @moduledoc """
  Issue 8, "a link whose peer disappears reconnects with backoff; its partition's commands end
  `ERROR` while it is down and work again once it is back" — for every link of the workstation.

  Each device test runs the whole simulated floor (`Vws.Sim.Floor`) with one device reached at a
  loopback endpoint of the test's. First a peer there accepts every connection and drops it at
  once (a terminal server whose device is off): the link must dial it less and less often — each
  gap at least the minimum doubled once more — as such a connection proves nothing
  (`Vws.Links.Backoff`; before it, all three links dialled it every 50 or 100 ms for ever). Then a
  `Vws.Sim.Line` to the simulator is put there, as a cable: the link connects by itself and the
  command is `DONE`. The line is then taken away (stopped: the endpoint refuses connections),
  and put back on the same endpoint. Whilst it is away:

    * the link dials again and again, each attempt announced by its `:connect_failed` telemetry
      event with the delay to the next one: more than one attempt, the delays growing (doubling
      up to the link's maximum), and no attempt earlier than announced;
    * a command of the partition behind it ends `ERROR` with the link's reason, promptly (the
      WC's own deadline is far away: nothing waits for the device to come back).

  Once the line is back the link reconnects by itself and the same command completes `DONE`.

  The WC link is tested the same way with SUN_COMM behind the line: the WC client reopens the
  link after a cut and after the line was away, and a status query then answers the true state
  of a command that completed while the WC could not see it.
  """
  use ExUnit.Case, async: true

  import Vws.Codecs.WC.Command, only: [pad4: 1]

  doctest Vws.Links.Backoff

  import Vws.Test.Eventually

  alias Vws.Peers.HydraulicController
  alias Vws.CEC.{Mailbox, SunComm}
  alias Vws.Sim.{Floor, Line, Plant}
  alias Vws.Test.{ObedientPartition, Workstation}
  alias Vws.Peers.WC.{Client, ClientError}

  # How long a command may take to end, when the link is down or up: far more than it needs.
  @command_ms 15_000

  # Per device: the link's telemetry prefix, how its failed attempts are told from others',
  # the WC command used, and what that command must end with while the device is away.
  @devices %{
    robot: %{
      event: [:vws, :ddcmp, :connect_failed],
      min_backoff: 100,
      command: {"R", "WHERE"},
      down: ~r/^ERROR VAL II LINK DOWN$/
    },
    ge2000: %{
      event: [:vws, :dnc, :connect_failed],
      min_backoff: 100,
      command: {"M", "STATUS"},
      down: ~r/^ERROR DNC LINK DOWN$/
    },
    daq1: %{
      event: [:vws, :hpib, :connect_failed],
      min_backoff: 50,
      command: {"G", "OPEN"},
      down: ~r/^ERROR DAQ #1 NOT CONNECTED$/
    },
    hydraulic: %{
      event: [:vws, :hpib, :connect_failed],
      min_backoff: 50,
      command: {"H", "RELEASE_PALLET"},
      down: ~r/^ERROR HYDRAULIC CONTROLLER NOT CONNECTED$/
    }
  }

  describe "a device link whose peer goes away" do
    for device <- [:robot, :ge2000, :daq1, :hydraulic] do
      @tag device: device
      test "#{device}: dials less and less often, its commands end ERROR, then DONE again",
           %{device: device} do
        spec = Map.fetch!(@devices, device)
        {letter, text} = spec.command

        # Before the device is reachable, something at its endpoint accepts each connection
        # and drops it at once (a terminal server whose device is off): every dial "succeeds",
        # none proves anything, so the waits between them grow as for a refused one.
        floor = shop_floor(device)
        flapper = floor.flapper
        accepted = collect_flaps(flapper, 5)
        assert_growing_gaps(accepted, spec.min_backoff)
        :ok = stop_supervised(:flapper)

        # the line to the device: the link connects by itself and the command is DONE
        start_line(floor.line_spec)
        assert eventually(fn -> run(floor.client, letter, text) == "DONE" end, 20_000, 50)

        # the line is taken away: nothing listens where the link dials
        attempts = attach_attempts(spec.event, floor, device)
        :ok = stop_supervised(:line)

        failures = collect_attempts(attempts, 4)
        assert_backoff(failures)

        # the partition's command ends ERROR with the link's reason, and does so promptly
        assert run(floor.client, letter, text) =~ spec.down

        # the line is back on the same endpoint: the link reconnects by itself
        start_line(floor.line_spec)
        assert eventually(fn -> run(floor.client, letter, text) == "DONE" end, 20_000, 50)
      end
    end
  end

  describe "the WC link" do
    setup do
      %{ws: ws, wc: wc} =
        Workstation.start(partitions: ObedientPartition.partitions(test: self()))

      assert eventually(fn -> SunComm.listening(ws) != nil end)
      listen = "loopback:wc-line-#{ws}"
      line_spec = %{id: :line, start: {Line, :start_link, [[listen: listen, target: wc]]}}
      line = start_line(line_spec)
      {:ok, client} = Client.connect(listen, connect_timeout: 5_000)
      %{ws: ws, client: client, wc_line: line, line_spec: line_spec}
    end

    test "cut mid-command: the client reconnects and the status query tells the true state", %{
      ws: ws,
      client: client,
      wc_line: line
    } do
      assert {:ok, [{"R", r}]} = Client.send_commands(client, [{"R", "MOVE 1"}])
      assert_receive {:executing, runner, ^r, "MOVE 1"}, 5_000

      # the line is cut while the command runs, and the command ends while the WC cannot see it
      :ok = Line.disconnect(line)
      assert eventually(fn -> Client.info(client).peer == nil end)
      send(runner, {:result, :done})
      assert eventually(fn -> Mailbox.command_status(ws, :robot) == {r, :done} end)

      # the next request opens the link again and gets the true answer
      assert Client.status(client, "ROBOT_CMD") == {:ok, pad4(r) <> "DONE"}
      assert Client.info(client).counters.reconnects == 1
      assert SunComm.info(ws).counters.connections == 2
      # and the command was run once, by the one string that carried it
      refute_received {:executing, _, _, _}
    end

    test "the line away: requests fail :closed at once; once it is back the client reconnects",
         %{ws: ws, client: client, line_spec: line_spec} do
      assert {:ok, [{"G", g}]} = Client.send_commands(client, [{"G", "ROTATE 90"}])
      assert_receive {:executing, runner, ^g, "ROTATE 90"}, 5_000

      :ok = stop_supervised(:line)
      send(runner, {:result, {:error, "FINGERS STUCK"}})

      assert eventually(fn ->
               Mailbox.command_status(ws, :gripper) == {g, {:error, "FINGERS STUCK"}}
             end)

      for _ <- 1..3 do
        assert {:error, %ClientError{reason: :closed}} = Client.status(client, "GRIPPER_CMD")
      end

      start_line(line_spec)

      assert Client.status(client, "GRIPPER_CMD") ==
               {:ok, pad4(g) <> "ERROR FINGERS STUCK"}

      # the set goes on with the next command through the new connection
      assert {:ok, [{"G", g2}]} = Client.send_commands(client, [{"G", "ROTATE 0"}])
      assert g2 == g + 1
      assert_receive {:executing, runner, ^g2, "ROTATE 0"}, 5_000
      send(runner, {:result, :done})
      assert Client.await_command(client, "G", g2, @command_ms) == :done
      refute_received {:executing, _, _, _}
    end
  end

  defmodule Flapper do
    @moduledoc false
    # Listens on an endpoint, accepts every connection and closes it at once, telling the test
    # `{:flapped, self(), monotonic ms}` for each.
    use GenServer

    def start_link(endpoint, test), do: GenServer.start_link(__MODULE__, {endpoint, test})

    @impl true
    def init({endpoint, test}) do
      Process.flag(:trap_exit, true)

      case Vws.Links.Transport.listen(endpoint) do
        {:ok, listener} ->
          Vws.Links.Transport.start_acceptor(listener, self(), :accepted)
          {:ok, %{listener: listener, test: test}}

        {:error, reason} ->
          {:stop, reason}
      end
    end

    @impl true
    def handle_info({:accepted, conn}, s) do
      send(s.test, {:flapped, self(), System.monotonic_time(:millisecond)})
      Vws.Links.Transport.close(conn)
      {:noreply, s}
    end

    def handle_info(_msg, s), do: {:noreply, s}

    @impl true
    def terminate(_reason, s), do: Vws.Links.Transport.close_listener(s.listener)
  end

  ## The floor, one device reached through an endpoint of the test's

  # The whole floor; the workstation reaches `device` at a loopback endpoint where the test puts
  # a line to the simulator (`start_line(floor.line_spec)`), or something else, or nothing.
  defp shop_floor(device) do
    ws = "reconnect-#{device}-#{System.unique_integer([:positive])}"

    start_supervised!(
      {Floor,
       workstation: ws,
       time_scale: 50,
       hydraulic: {HydraulicController, []},
       ge2000: true,
       robot: true,
       mhs: true}
    )

    :ok = HydraulicController.await_ready(Floor.hydraulic_controller(ws), 10_000)
    :ok = Plant.set_part(Floor.plant(ws), :tray1, true)

    devices = Floor.devices(ws)
    endpoint = "loopback:device-#{ws}"

    line_spec = %{
      id: :line,
      start: {Line, :start_link, [[listen: endpoint, target: Keyword.fetch!(devices, device)]]}
    }

    # there from the start, so that the link's first dial meets it
    flapper = start_flapper(endpoint)

    %{ws: ws, wc: wc} =
      Workstation.start(
        id: ws,
        devices: Keyword.put(devices, device, endpoint),
        partitions: [robot: [options: [command_timeout: 5_000, motion_timeout: 10_000]]]
      )

    assert eventually(fn -> SunComm.listening(ws) != nil end)
    {:ok, client} = Client.connect(wc)
    %{ws: ws, client: client, line_spec: line_spec, endpoint: endpoint, flapper: flapper}
  end

  # Starts a child that listens on an endpoint a stopped one has just let go of.
  defp start_line(spec) do
    {:ok, pid} =
      Enum.find_value(1..100, fn _ ->
        case start_supervised(spec) do
          {:ok, pid} ->
            {:ok, pid}

          {:error, _already_listening} ->
            Process.sleep(10)
            nil
        end
      end)

    pid
  end

  defp start_flapper(endpoint) do
    start_line(%{id: :flapper, start: {Flapper, :start_link, [endpoint, self()]}})
  end

  defp collect_flaps(flapper, n) do
    for _ <- 1..n do
      assert_receive {:flapped, ^flapper, at}, 20_000
      at
    end
  end

  # Each wait at least double the one before, from `min` (a timer never fires early, so this
  # holds however slow the machine): gap i (from 0) is at least min * 2^i.
  defp assert_growing_gaps(times, min) do
    gaps = for [t0, t1] <- Enum.chunk_every(times, 2, 1, :discard), do: t1 - t0

    for {gap, i} <- Enum.with_index(gaps) do
      assert gap >= min * Integer.pow(2, i),
             "the link dialled again #{gap} ms after a connection that proved nothing " <>
               "(gaps #{inspect(gaps, charlists: :as_lists)}, each should be at least #{min} ms doubled #{i} times)"
    end
  end

  # Sends one command and awaits its end: "DONE" or the CEC's "ERROR <reason>".
  defp run(client, letter, text) do
    {:ok, [{^letter, n}]} = Client.send_commands(client, [{letter, text}])

    case Client.await_command(client, letter, n, @command_ms, poll_interval: 20) do
      :done ->
        "DONE"

      {:error, %ClientError{reason: :command_failed, data: %{status: status}}} ->
        status

      {:error, error} ->
        flunk("#{letter} #{text} did not end: #{Exception.message(error)}")
    end
  end

  ## Watching the link dial

  # Every failed connection attempt of the link to `endpoint`, as {monotonic ms, retry_in ms}.
  defp attach_attempts(event, floor, device) do
    test = self()
    id = {__MODULE__, device, make_ref()}
    endpoint = floor.endpoint

    :ok =
      Vws.Telemetry.attach(
        id,
        event,
        fn _event, %{retry_in: retry_in}, meta, _config ->
          if to_string(meta.endpoint) == endpoint,
            do: send(test, {:connect_failed, id, System.monotonic_time(:millisecond), retry_in})
        end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
    id
  end

  defp collect_attempts(id, n) do
    for _ <- 1..n do
      assert_receive {:connect_failed, ^id, at, retry_in}, 20_000
      {at, retry_in}
    end
  end

  # More than one attempt; the announced delays never shrink and grow until they reach a
  # ceiling; no attempt came before the delay announced by the previous one (a timer never
  # fires early), so the gaps between attempts do not shrink below the growing delays either.
  defp assert_backoff(failures) do
    assert length(failures) > 1
    delays = Enum.map(failures, &elem(&1, 1))

    for [a, b] <- Enum.chunk_every(delays, 2, 1, :discard) do
      assert b >= a, "delays shrank: #{inspect(delays, charlists: :as_lists)}"
    end

    assert Enum.uniq(delays) != [hd(delays)] or length(delays) == 1,
           "a constant retry interval is no backoff: #{inspect(delays, charlists: :as_lists)}"

    for [{t0, delay}, {t1, _}] <- Enum.chunk_every(failures, 2, 1, :discard) do
      assert t1 - t0 >= delay, "an attempt came #{t1 - t0} ms after one announcing #{delay} ms"
    end
  end
end
