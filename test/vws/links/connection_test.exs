defmodule Vws.Links.ConnectionTest do
  # The connection shell of every driver: the wire (dial, back-off, transport messages, loss)
  # and the caller's deadline over a process alias. The drivers' own tests cover them in use.
  use ExUnit.Case, async: true

  alias Vws.Links.{Connection, Transport}

  # A driver in miniature: takes requests as Connection.call/3 sends them and answers each
  # `{:echo, term, after_ms}` that long after it came (never, for :never), and tells the test
  # every deadline it was given.
  defmodule Echo do
    @behaviour :gen_statem
    alias Vws.Links.Connection

    def start_link(test), do: :gen_statem.start_link(__MODULE__, test, [])
    @impl true
    def callback_mode, do: :handle_event_function
    @impl true
    def init(test), do: {:ok, :up, test}

    @impl true
    def handle_event(:cast, {Connection, _, _, _} = call, _state, _test),
      do: {:keep_state_and_data, [Connection.as_call(call)]}

    def handle_event({:call, from}, {:deadline, deadline, {:echo, term, wait}}, _, test) do
      send(test, {:deadline, deadline})

      case wait do
        :never -> :keep_state_and_data
        0 -> {:keep_state_and_data, [{:reply, from, term}]}
        ms -> {:keep_state_and_data, [{{:timeout, make_ref()}, ms, {from, term}}]}
      end
    end

    def handle_event({:call, _from}, {:deadline, _, :stop}, _, _test), do: {:stop, :told}

    def handle_event({:timeout, _}, {from, term}, _, test) do
      send(test, :answered_late)
      {:keep_state_and_data, [{:reply, from, term}]}
    end
  end

  describe "caller deadlines" do
    test "the reply comes back, and the driver is given the caller's deadline" do
      {:ok, echo} = Echo.start_link(self())
      before = System.monotonic_time(:millisecond)
      assert Connection.call(echo, {:echo, :pong, 0}, 5_000) == {:ok, :pong}
      assert_received {:deadline, deadline}

      assert deadline >= before + 5_000 and
               deadline <= System.monotonic_time(:millisecond) + 5_000

      assert Connection.call(echo, {:echo, :pong, 0}, :infinity) == {:ok, :pong}
      assert_received {:deadline, :infinity}
    end

    test "a reply after the deadline never reaches the caller's mailbox" do
      {:ok, echo} = Echo.start_link(self())
      assert Connection.call(echo, {:echo, :late, 100}, 20) == {:error, :timeout}
      # the driver answers later, to an alias that is gone: nothing arrives
      assert_receive :answered_late, 5_000
      assert_received {:deadline, _}
      :sys.get_state(echo)
      refute_receive {_, :late}, 200
      assert Process.info(self(), :messages) == {:messages, []}
    end

    test "a driver that ends, or is not there, is an error, never an exit" do
      {:ok, echo} = Echo.start_link(self())
      Process.unlink(echo)
      assert {:error, {:exit, :told}} = Connection.call(echo, :stop, 5_000)
      assert {:error, {:exit, :noproc}} = Connection.call(echo, {:echo, :x, 0}, 5_000)
      assert {:error, {:exit, :noproc}} = Connection.call(:no_such_driver, {:echo, :x, 0}, 100)
    end

    test "send_request/3 and check_response/2: the reply once, other messages are not it" do
      {:ok, echo} = Echo.start_link(self())
      req = Connection.send_request(echo, {:echo, :async, 0}, 5_000)
      other = Connection.send_request(echo, {:echo, :other, :never}, 5_000)

      reply = receive(do: ({[:alias | _], :async} = m -> m))
      assert Connection.check_response(reply, other) == :no_reply
      assert Connection.check_response(:unrelated, req) == :no_reply
      assert Connection.check_response(reply, req) == {:ok, :async}

      gone = Connection.send_request(:no_such_driver, :x, 100)
      down = receive(do: ({:DOWN, _, _, _, _} = m -> m))
      assert Connection.check_response(down, gone) == {:error, {:exit, :noproc}}
    end

    test "deadline arithmetic" do
      assert Connection.deadline(:infinity) == :infinity
      assert Connection.remaining(:infinity) == :infinity
      refute Connection.expired?(:infinity)
      past = Connection.deadline(0)
      assert Connection.remaining(past) == 0 and Connection.expired?(past)
      future = Connection.deadline(60_000)
      assert Connection.remaining(future) > 59_000 and not Connection.expired?(future)
    end
  end

  describe "the wire" do
    setup do
      endpoint = "loopback:connection-test-#{System.unique_integer([:positive])}"
      %{endpoint: endpoint}
    end

    test "a dial that fails waits longer each time, tells telemetry and keeps the reason", ctx do
      handler = "connection-test-#{inspect(self())}"
      me = self()

      Vws.Telemetry.attach(
        handler,
        [:vws, :dnc, :connect_failed],
        fn _event, measurements, metadata, _ -> send(me, {:failed, measurements, metadata}) end,
        nil
      )

      on_exit(fn -> Vws.Telemetry.detach(handler) end)

      c =
        Connection.new(
          endpoint: ctx.endpoint,
          backoff: {10, 25},
          telemetry: {[:vws, :dnc], %{link: :here, role: :cec, workstation: nil}}
        )

      {:error, _, w1, c} = Connection.connect(c)
      {:error, _, w2, c} = Connection.connect(c)
      {:error, reason, w3, c} = Connection.connect(c)
      assert [w1, w2, w3] == [10, 20, 25]
      assert c.failures == 3 and c.last_error == {:connect, reason}
      refute Connection.connected?(c)

      assert_received {:failed, %{count: 1, retry_in: 10}, %{link: :here, endpoint: endpoint}}
      assert endpoint == ctx.endpoint
    end

    test "connected: data is classified and the next chunk armed; a loss closes and waits", ctx do
      {:ok, listener} = Transport.listen(ctx.endpoint)
      c = Connection.new(endpoint: ctx.endpoint, backoff: {10, 40})
      {:ok, c} = Connection.connect(c)
      {:ok, peer} = Transport.accept(listener, 1_000)
      assert Connection.connected?(c) and c.connects == 1

      # a lost connection that never proved itself waits longer next time; one that did, not
      :ok = Transport.send(peer, "one")
      assert {:data, "one"} = Connection.handle_message(c, receive(do: (m -> m)))
      :ok = Transport.send(peer, "two")
      assert {:data, "two"} = Connection.handle_message(c, receive(do: (m -> m)))
      assert Connection.handle_message(c, :something_else) == :unknown

      :ok = Transport.close(peer)
      assert {:closed, :closed} = Connection.handle_message(c, receive(do: (m -> m)))
      {wait, c} = Connection.lost(c, :closed)
      assert wait == 10 and not Connection.connected?(c)
      assert Connection.handle_message(c, :anything) == :unknown
      assert Connection.send(c, "x") == {:error, :not_connected}

      {:ok, c} = Connection.connect(c)
      {:ok, _peer} = Transport.accept(listener, 1_000)
      c = Connection.alive(c)
      assert Connection.next_wait(c) == 10
      assert {20, _} = c |> Connection.wait() |> elem(1) |> Connection.wait()
    end

    test "the events a driver has the shell emit are in the telemetry catalogue" do
      # the shell relays names it is given (`@telemetry_relay`): each driver's are checked here
      reported = [
        {[:vws, :ddcmp], [:connect_failed]},
        {[:vws, :dnc], [:connect_failed, :connected, :disconnected]},
        {[:vws, :hpib], [:connect_failed]}
      ]

      for {prefix, events} <- reported,
          event <- events,
          do: assert((prefix ++ [event]) in Vws.Telemetry.events())
    end
  end

  describe "option types" do
    test "endpoints, back-offs and connections are checked with words" do
      assert {:ok, "tcp://h:1"} = Connection.check_endpoint("tcp://h:1")
      assert {:error, "expected an endpoint" <> _} = Connection.check_endpoint("ftp://h")
      assert {:ok, {0, 5}} = Connection.check_backoff({0, 5})
      assert {:error, _} = Connection.check_backoff({5, 1})
      assert {:error, _} = Connection.check_backoff(100)
      assert {:error, _} = Connection.check_conn(self())
    end
  end
end
