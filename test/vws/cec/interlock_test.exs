defmodule Vws.CEC.InterlockTest do
  use ExUnit.Case, async: true

  alias Vws.CEC.{Interlock, Mailbox}

  doctest Interlock

  setup do
    ws = "interlock-#{System.unique_integer([:positive])}"
    start_supervised!({Mailbox.Owner, workstation: ws})
    %{ws: ws}
  end

  test "a lease excludes what it must and shares what it may", %{ws: ws} do
    assert Interlock.acquire(ws, :table, :robot, 0) == :ok
    assert Interlock.acquire(ws, :table, :fixture, 0) == :ok
    assert Interlock.acquire(ws, :table, :monarch, 0) == {:error, "INTERLOCK TABLE HELD BY ROBOT"}
    assert Interlock.acquire(ws, :tray1, :mhs, 0) == :ok
    assert Interlock.acquire(ws, :tray1, :robot, 0) == {:error, "INTERLOCK TRAY1 HELD BY MHS"}
    assert Interlock.acquire(ws, :tray2, :robot, 0) == :ok

    assert Vws.Ops.Inspect.format_leases(Interlock.held(ws)) ==
             "TABLE=ROBOT,FIXTURE TRAY1=MHS TRAY2=ROBOT"

    :ok = Interlock.release(ws, :table, :robot)
    :ok = Interlock.release(ws, :table, :fixture)
    assert Interlock.acquire(ws, :table, :monarch, 0) == :ok

    assert Interlock.acquire(ws, :table, :fixture, 0) ==
             {:error, "INTERLOCK TABLE HELD BY MONARCH"}

    assert Interlock.holder(ws, :table) == :monarch
    refute Interlock.compatible?(:tray1, :robot, :mhs)
    assert Interlock.compatible?(:table, :fixture, :robot)
  end

  test "a waiting requester is woken by the release, not by its next try", %{ws: ws} do
    :ok = Interlock.acquire(ws, :tray1, :mhs, 0)
    me = self()

    # a try every minute: only the release's event can let it in within the bound below
    spawn_link(fn ->
      send(me, {:acquired, Interlock.acquire(ws, :tray1, :robot, 120_000, retry_ms: 60_000)})
    end)

    # it has tried once and waits (its request withdrawn, the MHS's lease in the way)
    Process.sleep(50)
    refute_received {:acquired, _}
    :ok = Interlock.release(ws, :tray1, :mhs, :all)
    assert_receive {:acquired, :ok}, 10_000
    assert Interlock.holders(ws, :tray1) == [:robot]
    # a reason given up that leaves the lease in place wakes nobody: still excluded
    :ok = Interlock.acquire(ws, :tray1, :robot, 0, as: :inside)
    :ok = Interlock.release(ws, :tray1, :robot, :inside)
    assert Interlock.acquire(ws, :tray1, :mhs, 0) == {:error, "INTERLOCK TRAY1 HELD BY ROBOT"}
  end

  test "an unverifiable wait still ends at its time limit, denied", %{ws: ws} do
    :ok = Interlock.acquire(ws, :tray1, :mhs, 0)
    started = System.monotonic_time(:millisecond)

    assert Interlock.acquire(ws, :tray1, :robot, 300, retry_ms: 100) ==
             {:error, "INTERLOCK TRAY1 HELD BY MHS"}

    assert System.monotonic_time(:millisecond) - started >= 300
    refute_received {:vws_event, ^ws, :interlock, _}
  end

  test "reasons: a lease ends when its last reason is given up", %{ws: ws} do
    :ok = Interlock.acquire(ws, :table, :robot, 0, as: :disabled)
    :ok = Interlock.acquire(ws, :table, :robot, 0, as: :inside)
    :ok = Interlock.acquire(ws, :table, :robot, 0, as: :inside)
    assert [%{volume: :table, holder: :robot, reasons: [:disabled, :inside]}] = Interlock.held(ws)
    assert Interlock.holds?(ws, :table, :robot, :inside)
    :ok = Interlock.release(ws, :table, :robot, :disabled)
    assert Interlock.holds?(ws, :table, :robot)
    refute Interlock.holds?(ws, :table, :robot, :disabled)
    :ok = Interlock.release(ws, :table, :robot, :inside)
    assert Interlock.held(ws) == []
    assert Vws.Ops.Inspect.format_leases(Interlock.held(ws)) == "NONE"
    # releasing what is not held is fine
    assert Interlock.release(ws, :tray2, :robot) == :ok
  end

  # Simulated time for the retry loop: `now` reads it, `pause` lets it pass at once (and
  # records each pause), so the count of tries does not depend on how busy the machine is.
  defp simulated_clock do
    {:ok, clock} = Agent.start_link(fn -> {0, []} end)
    now = fn -> Agent.get(clock, &elem(&1, 0)) end
    pause = fn ms -> Agent.update(clock, fn {t, ps} -> {t + ms, [ms | ps]} end) end
    pauses = fn -> Agent.get(clock, &Enum.reverse(elem(&1, 1))) end
    {{now, pause}, pauses}
  end

  test "a refused request is tried again about four times a second until the timeout", %{ws: ws} do
    me = self()
    check = fn -> send(me, :read) && {:error, "MACHINE ACTIVE"} end
    {clock, pauses} = simulated_clock()

    assert Interlock.acquire(ws, :table, :robot, 1_000, check: check, clock: clock) ==
             {:error, "INTERLOCK TABLE MACHINE ACTIVE"}

    tries =
      length(
        for _ <- 1..20,
            (receive do
               :read -> true
             after
               0 -> false
             end),
            do: 1
      )

    # at 0, ~250, ~500, ~750 and ~1000 ms (with ±20 % jitter): every pause but the last (cut
    # to the time left) is 200..300 ms, and together they reach the timeout: 5 or 6 tries
    assert tries in 5..6
    pauses = pauses.()
    assert length(pauses) == tries - 1
    assert Enum.all?(Enum.drop(pauses, -1), &(&1 in 200..300))
    assert Enum.sum(pauses) == 1_000
    # a request that was refused leaves nothing behind
    assert :ets.match_object(Mailbox.table(ws), {{:interlock, :_, :_}, :_}) == []
  end

  test "on the monotonic clock, a refused request waits out its timeout", %{ws: ws} do
    t0 = System.monotonic_time(:millisecond)
    check = fn -> {:error, "MACHINE ACTIVE"} end
    assert {:error, _} = Interlock.acquire(ws, :table, :robot, 300, check: check, retry_ms: 50)
    assert System.monotonic_time(:millisecond) - t0 >= 300
  end

  test "telemetry: acquired, refused (with the tries) and released", %{ws: ws} do
    me = self()
    id = {__MODULE__, ws}

    :ok =
      Vws.Telemetry.attach_many(
        id,
        [
          [:vws, :interlock, :acquired],
          [:vws, :interlock, :refused],
          [:vws, :interlock, :released]
        ],
        fn event, m, meta, _ -> if meta.workstation == ws, do: send(me, {event, m, meta}) end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(id) end)
    :ok = Interlock.acquire(ws, :tray1, :mhs, 0)
    assert_received {[:vws, :interlock, :acquired], %{tries: 1}, %{holder: :mhs, volume: :tray1}}
    {clock, pauses} = simulated_clock()
    opts = [retry_ms: 20, as: :inside, clock: clock]
    {:error, _} = Interlock.acquire(ws, :tray1, :robot, 100, opts)

    assert_received {[:vws, :interlock, :refused], %{tries: tries, wait_ms: wait},
                     %{holder: :robot, reason: :inside, why: "HELD BY MHS"}}

    # 16..24 ms pauses until 100 ms have passed: 6 to 8 tries, the wait exactly the timeout
    assert tries in 6..8 and tries == length(pauses.()) + 1 and wait == 100
    :ok = Interlock.release(ws, :tray1, :mhs)
    assert_received {[:vws, :interlock, :released], %{count: 1}, %{holder: :mhs, reason: :all}}
  end

  test "a request waits for the holder to let go", %{ws: ws} do
    :ok = Interlock.acquire(ws, :tray1, :mhs, 0)

    spawn_link(fn ->
      Process.sleep(100)
      Interlock.release(ws, :tray1, :mhs)
    end)

    t0 = System.monotonic_time(:millisecond)
    assert Interlock.acquire(ws, :tray1, :robot, 2_000, retry_ms: 20) == :ok
    assert System.monotonic_time(:millisecond) - t0 >= 100
    assert Interlock.holders(ws, :tray1) == [:robot]
  end

  test "the conditions are read with the request posted, and a failing one denies", %{ws: ws} do
    me = self()

    check = fn ->
      # while we read, the other side sees our request and must stay out
      send(me, {:other, Interlock.acquire(ws, :table, :monarch, 0)})
      :ok
    end

    assert Interlock.acquire(ws, :table, :robot, 0, check: check) == :ok
    assert_received {:other, {:error, "INTERLOCK TABLE HELD BY ROBOT"}}
  end

  test "a request left by a process that died is cleared by the next one", %{ws: ws} do
    dead = spawn(fn -> :ok end)
    ref = Process.monitor(dead)
    assert_receive {:DOWN, ^ref, _, _, _}

    :ets.insert(
      Mailbox.table(ws),
      {{:interlock, :table, :monarch},
       %{state: :requesting, pid: dead, since: 0, order: 0, reasons: [:cycle]}}
    )

    assert Interlock.acquire(ws, :table, :robot, 0) == :ok
    assert Interlock.holders(ws, :table) == [:robot]
  end

  test "M1/M2: two sides racing for a volume are never both in it", %{ws: ws} do
    table = Mailbox.table(ws)
    me = self()

    racer = fn holder, other ->
      spawn_link(fn ->
        violations =
          for _ <- 1..300, reduce: 0 do
            acc ->
              case Interlock.acquire(ws, :table, holder, 0) do
                :ok ->
                  # inside: the other side must not be
                  bad =
                    match?(
                      [{_, %{state: :held}}],
                      :ets.lookup(table, {:interlock, :table, other})
                    )

                  Interlock.release(ws, :table, holder)
                  if bad, do: acc + 1, else: acc

                {:error, _} ->
                  acc
              end
          end

        send(me, {:done, holder, violations})
      end)
    end

    racer.(:robot, :monarch)
    racer.(:monarch, :robot)
    racer.(:fixture, :monarch)

    for _ <- 1..3 do
      assert_receive {:done, _holder, 0}, 10_000
    end
  end

  test "the table's conditions deny what they cannot read", %{ws: ws} do
    check = Vws.Partitions.TableConditions.check(ws, machine_stale_ms: 100, sensor_timeout_ms: 50)
    assert check.() == {:error, "MACHINE STATUS NO DATA"}
    Mailbox.put_device(ws, 8, "NO DATA (NO LINK TO GE-2000)")
    assert check.() == {:error, "MACHINE STATUS NO DATA (NO LINK TO GE-2000)"}
    Mailbox.put_device(ws, 8, "ACTIVE")
    assert check.() == {:error, "MACHINE ACTIVE"}
    Mailbox.put_device(ws, 8, "IDLE")
    # no poll of DAQ #1 ever came
    assert check.() == {:error, "PARK SWITCH NOT READ (DAQ #1 NOT READ YET)"}
    Process.sleep(120)
    assert {:error, "MACHINE STATUS STALE (" <> _} = check.()

    assert {:error, "INTERLOCK TABLE MACHINE STATUS STALE (" <> _} =
             Interlock.acquire(ws, :table, :fixture, 0, check: check)
  end
end
