defmodule Vws.Links.HPIBTest do
  use ExUnit.Case, async: true
  doctest Vws.Links.HPIB.Error

  alias Vws.Links.{HPIB, Transport}
  alias Vws.Links.HPIB.Error
  import Vws.Test.Eventually

  doctest Vws.Links.HPIB

  # The test plays the instrument on a loopback endpoint, so it decides what is answered, when,
  # and whether at all.
  setup do
    name = "hpib-#{System.unique_integer([:positive])}"
    %{endpoint: "loopback:" <> name, bus: name}
  end

  defp start_device(ctx, opts \\ []) do
    start_supervised!(
      {HPIB, [bus: ctx.bus, address: 9, endpoint: ctx.endpoint, backoff: {10, 50}] ++ opts}
    )

    {ctx.bus, 9}
  end

  defp instrument(ctx) do
    {:ok, listener} = Transport.listen(ctx.endpoint)
    listener
  end

  defp accept(listener) do
    {:ok, conn} = Transport.accept(listener, 2_000)
    :ok = Transport.activate(conn)
    conn
  end

  # The next complete lines the instrument received (waits for `n` of them). Other messages
  # (task replies) are put back afterwards.
  defp recv_lines(conn, n, acc \\ "", other \\ []) do
    lines = String.split(acc, "\n", trim: true)

    if length(lines) >= n and String.ends_with?(acc, "\n") do
      other |> Enum.reverse() |> Enum.each(&send(self(), &1))
      lines
    else
      receive do
        msg ->
          case Transport.handle_message(conn, msg) do
            {:data, bytes} ->
              Transport.activate(conn)
              recv_lines(conn, n, acc <> bytes, other)

            :unknown ->
              recv_lines(conn, n, acc, [msg | other])

            closed_or_error ->
              flunk("instrument connection: #{inspect(closed_or_error)}")
          end
      after
        2_000 -> flunk("instrument received #{inspect(acc)} only")
      end
    end
  end

  defp nothing_received?(conn, ms) do
    receive do
      msg ->
        case Transport.handle_message(conn, msg) do
          :unknown -> flunk("unexpected message #{inspect(msg)}")
          _data_or_close -> false
        end
    after
      ms -> true
    end
  end

  defp closed?(conn) do
    receive do
      msg -> Transport.handle_message(conn, msg) == :closed
    after
      2_000 -> false
    end
  end

  test "a transaction is sent back to back and each query gets its own answer, in order", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)

    task =
      Task.async(fn ->
        HPIB.transaction(dev, [
          {:rout_clos, [201]},
          {:meas_volt_dc?, [101, 102]},
          {:rout_clos?, [201]},
          :idn?
        ])
      end)

    assert recv_lines(conn, 4) == [
             "ROUT:CLOS (@201)",
             "MEAS:VOLT:DC? (@101,102)",
             "ROUT:CLOS? (@201)",
             "*IDN?"
           ]

    Transport.send(conn, "+5.0E+00,-1.0E-03\n1\nACME,3497A,1,1.0\n")

    assert Task.await(task) ==
             {:ok,
              [
                :ok,
                [5.0, -0.001],
                [true],
                %{manufacturer: "ACME", model: "3497A", serial: "1", firmware: "1.0"}
              ]}
  end

  test "a command without a response is done once it is written", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)
    assert HPIB.write(dev, {:rout_open, [205]}) == :ok
    assert recv_lines(conn, 1) == ["ROUT:OPEN (@205)"]
  end

  test "while the endpoint refuses, requests fail at once; it connects when it can", ctx do
    dev = start_device(ctx)

    assert {:error, %Error{reason: :not_connected, address: 9}} = HPIB.query(dev, :idn?, 5_000)

    listener = instrument(ctx)
    assert HPIB.await_connected(dev, 2_000) == :ok
    conn = accept(listener)
    task = Task.async(fn -> HPIB.query(dev, {:rout_clos?, [207]}) end)
    assert recv_lines(conn, 1) == ["ROUT:CLOS? (@207)"]
    Transport.send(conn, "0\n")
    assert Task.await(task) == {:ok, [false]}
  end

  test "await_connected waits for the device to connect, without asking it over and over", ctx do
    dev = start_device(ctx)
    me = self()

    waiter =
      spawn_link(fn ->
        receive do
          {:go, limit} -> send(me, {:awaited, HPIB.await_connected(dev, limit)})
        end
      end)

    # the waiter's requests to the device: one, answered when it is connected (it asked for its
    # state every 5 ms)
    :erlang.trace_pattern({Vws.Links.Connection, :call, 3}, true, [:local])
    :erlang.trace(waiter, true, [:call])

    try do
      send(waiter, {:go, 30_000})
      Process.sleep(100)
      refute_received {:awaited, _}
      _listener = instrument(ctx)
      assert_receive {:awaited, :ok}, 30_000
    after
      :erlang.trace_pattern({Vws.Links.Connection, :call, 3}, false, [:local])
    end

    calls =
      Stream.repeatedly(fn ->
        receive do
          {:trace, ^waiter, :call, {Vws.Links.Connection, :call, [_, request, _]}} -> request
        after
          0 -> nil
        end
      end)
      |> Enum.take_while(& &1)

    assert calls == [:await_connected]
    # not started: no wait at all
    assert HPIB.await_connected({"no-such-bus", 9}, 5_000) == :timeout
  end

  test "no answer in time: a timeout error, the connection is dropped and made again", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx, retries: 0)
    conn = accept(listener)

    assert {:error, %Error{reason: :timeout, detail: 50} = error} =
             HPIB.query(dev, {:meas_res?, [117]}, 50)

    assert Exception.message(error) =~ "did not answer within 50 ms"
    assert recv_lines(conn, 1) == ["MEAS:RES? (@117)"]
    # the old connection is closed so that its late answer can never be read as a new one
    assert closed?(conn)
    conn2 = accept(listener)
    assert HPIB.await_connected(dev, 2_000) == :ok

    task = Task.async(fn -> HPIB.query(dev, {:meas_res?, [117]}) end)
    assert recv_lines(conn2, 1) == ["MEAS:RES? (@117)"]
    Transport.send(conn2, "+3.5E+02\n")
    assert Task.await(task) == {:ok, [350.0]}
    assert %{timeouts: 1, connects: 2} = HPIB.info(dev)
  end

  test "an answer that does not answer the query is a bad_response; the next one works", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx, retries: 0)
    conn = accept(listener)

    task = Task.async(fn -> HPIB.query(dev, {:meas_volt_dc?, [101, 102]}) end)
    assert recv_lines(conn, 1) == ["MEAS:VOLT:DC? (@101,102)"]
    Transport.send(conn, "+5.0E+00\n")

    assert {:error,
            %Error{reason: :bad_response, detail: %Vws.Codecs.SCPI.Error{reason: :bad_response}}} =
             Task.await(task)

    task = Task.async(fn -> HPIB.query(dev, {:rout_clos?, [201]}) end)
    assert recv_lines(conn, 1) == ["ROUT:CLOS? (@201)"]
    Transport.send(conn, "1\n")
    assert Task.await(task) == {:ok, [true]}
  end

  test "the connection lost while waiting ends the request :closed; it reconnects", ctx do
    # (not tried again, repeatable as it is: a peer that closes is not a damaged line)
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)
    task = Task.async(fn -> HPIB.query(dev, :idn?) end)
    assert recv_lines(conn, 1) == ["*IDN?"]
    Transport.close(conn)
    assert {:error, %Error{reason: :closed}} = Task.await(task)
    _conn2 = accept(listener)
    assert HPIB.await_connected(dev, 2_000) == :ok
  end

  describe "a damaged or missing answer to a repeatable request" do
    setup ctx do
      test_pid = self()
      handler = "hpib-retry-#{ctx.bus}"
      bus = ctx.bus

      :ok =
        Vws.Telemetry.attach(
          handler,
          [:vws, :hpib, :retry],
          fn _, m, md, _ ->
            if md.bus == bus, do: send(test_pid, {:retry, m.count, md.reason, md.try})
          end,
          nil
        )

      on_exit(fn -> Vws.Telemetry.detach(handler) end)
      :ok
    end

    test "a damaged answer: asked again on a new connection, the good answer returned", ctx do
      listener = instrument(ctx)
      dev = start_device(ctx)
      conn = accept(listener)

      task = Task.async(fn -> HPIB.query(dev, {:meas_volt_dc?, [101, 102]}) end)
      assert recv_lines(conn, 1) == ["MEAS:VOLT:DC? (@101,102)"]
      # one reading where two were asked (a comma damaged on the line)
      Transport.send(conn, "+5.0E+00+1.0E+00\n")
      assert_receive {:retry, 1, :bad_response, 1}
      # a device clear: the old connection closed, the request sent again on a new one
      assert closed?(conn)
      conn2 = accept(listener)
      assert recv_lines(conn2, 1) == ["MEAS:VOLT:DC? (@101,102)"]
      Transport.send(conn2, "+5.0E+00,+1.0E+00\n")
      assert Task.await(task) == {:ok, [5.0, 1.0]}
      assert %{retried: 1, connects: 2} = HPIB.info(dev)
    end

    test "no answer, then a damaged one: each try waits its share of the time; the last answers",
         ctx do
      listener = instrument(ctx)
      dev = start_device(ctx)
      conn = accept(listener)

      task =
        Task.async(fn ->
          HPIB.transaction(dev, [{:rout_clos, [201]}, {:rout_clos?, [201]}], 3_000)
        end)

      assert recv_lines(conn, 2) == ["ROUT:CLOS (@201)", "ROUT:CLOS? (@201)"]
      # silence: the first try gives up after its third of the time
      assert_receive {:retry, 1, :timeout, 1}, 2_500
      conn2 = accept(listener)
      assert recv_lines(conn2, 2) == ["ROUT:CLOS (@201)", "ROUT:CLOS? (@201)"]
      Transport.send(conn2, "2\n")
      assert_receive {:retry, 1, :bad_response, 2}, 2_500
      conn3 = accept(listener)
      assert recv_lines(conn3, 2) == ["ROUT:CLOS (@201)", "ROUT:CLOS? (@201)"]
      Transport.send(conn3, "1\n")
      assert Task.await(task) == {:ok, [:ok, [true]]}
      assert %{retried: 2, timeouts: 1} = HPIB.info(dev)
    end

    test "the tries run out: the last failure is returned", ctx do
      listener = instrument(ctx)
      dev = start_device(ctx, retries: 1)
      conn = accept(listener)
      task = Task.async(fn -> HPIB.query(dev, :idn?) end)
      assert recv_lines(conn, 1) == ["*IDN?"]
      Transport.send(conn, "garbage\n")
      conn2 = accept(listener)
      assert recv_lines(conn2, 1) == ["*IDN?"]
      Transport.send(conn2, "more garbage\n")
      assert {:error, %Error{reason: :bad_response}} = Task.await(task)
      assert_received {:retry, 1, :bad_response, 1}
      refute_received {:retry, _, _, 2}
    end

    test "a request that cannot be repeated is never sent twice", ctx do
      listener = instrument(ctx)
      dev = start_device(ctx)
      conn = accept(listener)
      # SYST:ERR? takes an error off the instrument's queue: asking again would lose one
      task = Task.async(fn -> HPIB.transaction(dev, [:clamp_pallet, :syst_err?]) end)
      assert recv_lines(conn, 2) == ["CLAMP_PALLET", "SYST:ERR?"]
      Transport.send(conn, "damaged\n")
      assert {:error, %Error{reason: :bad_response}} = Task.await(task)
      refute_received {:retry, _, _, _}
      assert HPIB.info(dev).retried == 0
    end
  end

  test "requests from several callers are served one at a time, in arrival order", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)

    tasks =
      for ch <- 201..205 do
        t = Task.async(fn -> HPIB.query(dev, {:rout_clos?, [ch]}) end)
        # each request is in the device's queue before the next one is made
        assert eventually(fn -> HPIB.info(dev).requests == ch - 200 end)
        t
      end

    for {ch, answer} <- Enum.zip(201..205, ["1", "0", "1", "0", "1"]) do
      assert recv_lines(conn, 1) == ["ROUT:CLOS? (@#{ch})"]
      Transport.send(conn, answer <> "\n")
    end

    assert Enum.map(tasks, &Task.await/1) ==
             [{:ok, [true]}, {:ok, [false]}, {:ok, [true]}, {:ok, [false]}, {:ok, [true]}]
  end

  test "a request whose time runs out while it waits behind another is never sent", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)
    first = Task.async(fn -> HPIB.query(dev, :idn?, 2_000) end)
    assert recv_lines(conn, 1) == ["*IDN?"]
    second = Task.async(fn -> HPIB.query(dev, {:meas_res?, [117]}, 20) end)
    assert eventually(fn -> HPIB.info(dev).queued == 1 end)
    Process.sleep(40)
    Transport.send(conn, "A,B,C,D\n")
    assert {:ok, %{model: "B"}} = Task.await(first)
    assert {:error, %Error{reason: :timeout}} = Task.await(second)
    # the instrument never saw the second one
    assert nothing_received?(conn, 100)
    assert HPIB.info(dev).state == :ready
  end

  test "send_request/check_response make a request without blocking", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)
    req = HPIB.send_request(dev, [{:rout_clos?, [210]}])
    assert recv_lines(conn, 1) == ["ROUT:CLOS? (@210)"]
    Transport.send(conn, "1\n")

    assert_receive msg
    assert HPIB.check_response(:something_else, req) == :no_reply
    assert HPIB.check_response(msg, req) == {:ok, [[true]]}
  end

  test "lines nobody asked for are counted and dropped", ctx do
    listener = instrument(ctx)
    dev = start_device(ctx)
    conn = accept(listener)
    assert HPIB.await_connected(dev, 2_000) == :ok
    Transport.send(conn, "+1.0E+00\n")
    assert eventually(fn -> HPIB.info(dev).unsolicited == 1 end)
  end

  test "an address with no device", ctx do
    assert {:error, %Error{reason: :no_device, address: 4}} = HPIB.query({ctx.bus, 4}, :idn?)
    req = HPIB.send_request({ctx.bus, 4}, [:idn?])
    assert_receive msg
    assert {:error, %Error{reason: :no_device}} = HPIB.check_response(msg, req)
  end

  test "addresses are 0..30 and commands must be of the SCPI subset", ctx do
    assert_raise Vws.Options.Error, ~r/HPIB option :address/, fn ->
      HPIB.start_link(bus: ctx.bus, address: 31, endpoint: ctx.endpoint)
    end

    assert_raise Vws.Options.Error, ~r/unknown HPIB option :adress/, fn ->
      HPIB.start_link(bus: ctx.bus, adress: 3, endpoint: ctx.endpoint)
    end

    assert_raise ArgumentError, fn -> HPIB.query({ctx.bus, 9}, {:meas_res?, []}) end
  end
end
