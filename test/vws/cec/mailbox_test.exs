defmodule Vws.CEC.MailboxTest do
  use ExUnit.Case, async: true
  doctest Vws.CEC.Events

  alias Vws.CEC.Mailbox

  setup do
    ws = "mbx-#{System.unique_integer([:positive])}"
    start_supervised!({Mailbox.Owner, workstation: ws})
    %{ws: ws}
  end

  test "the seed's layout: device locations 1-14, command locations 34-39", %{ws: ws} do
    assert Enum.map(Mailbox.partitions(), &Mailbox.command_location/1) == Enum.to_list(34..39)
    assert Mailbox.command_location(:robot) == 34
    assert Mailbox.device_location("VISE") == 3
    assert Mailbox.device_location("SPARE") == nil
    for loc <- 1..14, do: assert({nil, _} = Mailbox.get_device(ws, loc))
    for p <- Mailbox.partitions(), do: assert(Mailbox.command_status(ws, p) == {nil, :none})
  end

  test "dispatch is refused while a command of the set is in flight", %{ws: ws} do
    assert :ok = Mailbox.dispatch(ws, :robot, 9, "WHERE")
    assert Mailbox.command_status(ws, :robot) == {9, :executing}
    assert Mailbox.cmd_in(ws, :robot) == {9, "WHERE"}
    assert {:busy, 9} = Mailbox.dispatch(ws, :robot, 10, "WHERE")
    assert :ok = Mailbox.dispatch(ws, :gripper, 4, "OPEN")
    assert :ok = Mailbox.finish(ws, :robot, 9, :done)
    assert Mailbox.command_status(ws, :robot) == {9, :done}
    assert :not_in_flight = Mailbox.finish(ws, :robot, 9, {:error, "AGAIN"})
    assert Mailbox.command_status(ws, :robot) == {9, :done}
  end

  test "finishing a command does not overwrite the answer of a newer one", %{ws: ws} do
    :ok = Mailbox.dispatch(ws, :robot, 9, "WHERE")
    Mailbox.put_status(ws, :robot, 10, {:error, "BUSY 0009"})
    :ok = Mailbox.finish(ws, :robot, 9, :done)
    assert Mailbox.command_status(ws, :robot) == {10, {:error, "BUSY 0009"}}
    assert Mailbox.in_flight(ws, :robot) == nil
  end

  test "concurrent dispatches of one set: exactly one wins", %{ws: ws} do
    results =
      1..50
      |> Task.async_stream(fn n -> Mailbox.dispatch(ws, :vacuum, n, "ON") end, max_concurrency: 50)
      |> Enum.map(fn {:ok, r} -> r end)

    assert Enum.count(results, &(&1 == :ok)) == 1
  end

  test "a process that keeps the table uses the new one once its owner is restarted", %{ws: ws} do
    old = Mailbox.keep_table(ws)
    assert Mailbox.table(ws) == old
    owner = Vws.Names.whereis(ws, :mailbox_owner)
    ref = Process.monitor(owner)
    Process.exit(owner, :kill)
    assert_receive {:DOWN, ^ref, _, _, :killed}
    # the test supervisor starts a new owner with a new table
    new = wait_for_new_table(ws, old, 500)
    assert new != old
    assert Mailbox.table(ws) == new
    Mailbox.put_device(ws, 1, "AFTER THE RESTART")
    assert {"AFTER THE RESTART", _} = Mailbox.get_device(ws, 1)
  end

  test "several locations are written at once, each change announced in order", %{ws: ws} do
    Mailbox.put_device(ws, 2, "SAME")
    Vws.CEC.Events.subscribe(ws, :mailbox)
    :ok = Mailbox.put_devices(ws, [{1, "ONE"}, {2, "SAME"}, {11, {:no_data, "X"}, :changed}])
    assert {"ONE", _} = Mailbox.get_device(ws, 1)
    assert {{:no_data, "X"}, _} = Mailbox.get_device(ws, 11)
    assert_receive {:vws_event, ^ws, :mailbox, {{:device, 1, "ONE"}, _}}
    assert_receive {:vws_event, ^ws, :mailbox, {{:device, 11, {:no_data, "X"}}, _}}
    refute_received {:vws_event, ^ws, :mailbox, {{:device, 2, _}, _}}
    assert_raise CaseClauseError, fn -> Mailbox.put_devices(ws, [{1, "TWO"}, {15, "NO SUCH"}]) end
    # nothing of a write with a bad location is written
    assert {"ONE", _} = Mailbox.get_device(ws, 1)
  end

  defp wait_for_new_table(ws, old, ms) do
    case Registry.lookup(Vws.Registry, {ws, :mailbox}) do
      [{_pid, table}] when table != old ->
        table

      _ when ms > 0 ->
        Process.sleep(10)
        wait_for_new_table(ws, old, ms - 10)
    end
  end

  test "a late answer is not written over what was written since it was asked", %{ws: ws} do
    Vws.CEC.Events.subscribe(ws, :mailbox)
    asked_at = System.monotonic_time(:millisecond)
    :ok = Mailbox.put_device(ws, 10, "PALLET CLAMPED")
    assert Mailbox.put_device_unless_newer(ws, 10, "PALLET NOT CLAMPED", asked_at) == :newer
    assert {"PALLET CLAMPED", _} = Mailbox.get_device(ws, 10)
    assert_receive {:vws_event, ^ws, :mailbox, {{:device, 10, "PALLET CLAMPED"}, _}}
    refute_received {:vws_event, ^ws, :mailbox, {{:device, 10, "PALLET NOT CLAMPED"}, _}}

    # asked after the last write: written, and announced
    Process.sleep(2)
    asked_at = System.monotonic_time(:millisecond)
    assert Mailbox.put_device_unless_newer(ws, 10, "PALLET NOT CLAMPED", asked_at) == :ok
    assert {"PALLET NOT CLAMPED", _} = Mailbox.get_device(ws, 10)
    assert_receive {:vws_event, ^ws, :mailbox, {{:device, 10, "PALLET NOT CLAMPED"}, _}}
  end

  test "a location not read yet takes an answer asked before that text was written", %{ws: ws} do
    asked_at = System.monotonic_time(:millisecond)
    :ok = Mailbox.put_device(ws, 8, "NO DATA (GE-2000 NOT READ YET)")
    assert Mailbox.put_device_unless_newer(ws, 8, "IDLE", asked_at) == :ok
    assert {"IDLE", _} = Mailbox.get_device(ws, 8)
    # and, once read, an older answer no longer does
    assert Mailbox.put_device_unless_newer(ws, 8, "ACTIVE", asked_at) == :newer
    assert {"IDLE", _} = Mailbox.get_device(ws, 8)
  end

  test "device values carry their age", %{ws: ws} do
    :ok = Mailbox.put_device(ws, 5, "VACUUM IS ON")
    assert {"VACUUM IS ON", age} = Mailbox.get_device(ws, 5)
    assert age >= 0
  end

  test "the iex table shows every location", %{ws: ws} do
    :ok = Mailbox.dispatch(ws, :robot, 9, "DO MOVE SAFE")
    Mailbox.put_device(ws, 3, "VISE IS UNLOCKED PART NOT IN VISE")
    text = Vws.Ops.Inspect.format_mailboxes(ws)
    assert text =~ "34  ROBOT     0009  EXECUTING"
    assert text =~ "0009 DO MOVE SAFE"
    assert text =~ "VISE IS UNLOCKED PART NOT IN VISE"
    assert text =~ "ok_to_proceed=0"
    assert text =~ "INTERLOCKS: NONE"
    :ok = Vws.CEC.Interlock.acquire(ws, :table, :robot, 0)
    assert Vws.Ops.Inspect.format_mailboxes(ws) =~ "INTERLOCKS: TABLE=ROBOT"
    assert [%{volume: :table, holder: :robot}] = Vws.Ops.Inspect.mailbox_snapshot(ws).interlocks

    assert ExUnit.CaptureIO.capture_io(fn -> Vws.Ops.Inspect.mailboxes(ws) end) =~
             "COMMAND STATUS"
  end

  test "locked/2 serialises read-modify-write sections", %{ws: ws} do
    :ets.insert(Mailbox.table(ws), {:counter, 0})

    1..100
    |> Task.async_stream(fn _ ->
      Mailbox.locked(ws, fn t ->
        [{_, n}] = :ets.lookup(t, :counter)
        :ets.insert(t, {:counter, n + 1})
      end)
    end)
    |> Stream.run()

    assert :ets.lookup(Mailbox.table(ws), :counter) == [{:counter, 100}]
  end

  test "an event never created cannot be caused", %{ws: ws} do
    assert Vws.CEC.Events.cause(ws, :nonexistent) == {:error, :no_such_event}
    assert Vws.CEC.Events.count(ws, :nonexistent) == nil
  end
end
