defmodule Vws.Links.Transport.SerialTest do
  # Real ttys: a socat-made pty pair stands in for a null-modem cable between two serial ports.
  use ExUnit.Case, async: true

  import Vws.TransportHelpers

  alias Vws.Links.Transport
  alias Vws.Links.Transport.Serial

  @moduletag :tty

  setup do
    pair = Vws.Test.PtyPair.start!()
    true = File.exists?(pair.a) and File.exists?(pair.b)
    pair
  end

  # Opens both ends and proves both socats are relaying before the test starts.
  defp open_both(%{a: a, b: b}, query \\ "baud=9600") do
    {:ok, end_a} = Transport.connect("tty:#{a}?#{query}")
    {:ok, end_b} = Transport.connect("tty:#{b}?#{query}")
    :ok = Transport.send(end_a, "ping")
    assert recv_exactly(end_b, 4) == "ping"
    :ok = Transport.send(end_b, "pong")
    assert recv_exactly(end_a, 4) == "pong"
    {end_a, end_b}
  end

  defp socat_pid(conn), do: conn.handle.os_pid

  test "bytes flow both ways, and closing ends socat", ctx do
    {end_a, end_b} = open_both(ctx)
    assert end_a.handle.backend == :socat
    assert Transport.peer(end_a) == "tty:#{ctx.a}?baud=9600&data_bits=8&parity=none&stop_bits=1"

    every_byte = Enum.into(0..255, <<>>, &<<&1>>)
    :ok = Transport.send(end_a, ["ENQ", every_byte])
    assert recv_exactly(end_b, 259) == "ENQ" <> every_byte
    :ok = Transport.send(end_b, every_byte)
    assert recv_exactly(end_a, 256) == every_byte

    for conn <- [end_a, end_b] do
      assert Serial.os_alive?(socat_pid(conn))
      assert Transport.close(conn) == :ok
      refute Serial.os_alive?(socat_pid(conn))
      assert Transport.close(conn) == :ok
      assert Transport.send(conn, "x") == {:error, %Vws.Links.Transport.Error{reason: :closed}}
    end
  end

  test "1 MB arrives intact and in order", ctx do
    {end_a, end_b} = open_both(ctx)
    data = :crypto.strong_rand_bytes(1_048_576)
    for <<chunk::binary-size(4096) <- data>>, do: :ok = Transport.send(end_a, chunk)
    assert recv_exactly(end_b, byte_size(data), 30_000) == data
    :ok = Transport.close(end_a)
    :ok = Transport.close(end_b)
  end

  test "bytes sent just before close still reach the line", ctx do
    {end_a, end_b} = open_both(ctx)
    data = :crypto.strong_rand_bytes(262_144)
    :ok = Transport.send(end_a, data)
    :ok = Transport.close(end_a)
    assert recv_exactly(end_b, byte_size(data), 30_000) == data
    :ok = Transport.close(end_b)
  end

  test "a serial line is always active: activate/1 is accepted and changes nothing", ctx do
    {end_a, end_b} = open_both(ctx)
    :ok = Transport.send(end_a, "unasked")
    port = end_b.handle.port
    assert_receive {^port, {:data, "unasked"}}, 5000
    assert Transport.activate(end_b) == :ok
    :ok = Transport.close(end_a)
    :ok = Transport.close(end_b)
  end

  test "controlling_process hands the port to another process", ctx do
    {end_a, end_b} = open_both(ctx)
    test = self()

    new_owner =
      spawn_link(fn ->
        receive do
          :go -> send(test, {:got, recv_exactly(end_b, 5)})
        end

        receive do
          :close -> send(test, {:closed, Transport.close(end_b)})
        end
      end)

    assert Transport.controlling_process(end_b, new_owner) == :ok
    refute end_b.handle.port in elem(Process.info(self(), :links), 1)

    assert Transport.controlling_process(end_b, self()) ==
             {:error, %Vws.Links.Transport.Error{reason: :not_owner}}

    :ok = Transport.send(end_a, "hello")
    send(new_owner, :go)
    assert_receive {:got, "hello"}, 5000
    send(new_owner, :close)
    assert_receive {:closed, :ok}, 5000
    refute Serial.os_alive?(socat_pid(end_b))
    :ok = Transport.close(end_a)
  end

  test "pulling the cable (the pty pair goes away) is said as such at both ends", ctx do
    {end_a, end_b} = open_both(ctx)
    System.cmd("kill", [Integer.to_string(ctx.cable_pid)])
    gone = {:error, %Vws.Links.Transport.Error{reason: :device_gone}}
    assert next(end_a) == gone
    assert next(end_b) == gone

    assert Exception.message(elem(gone, 1)) ==
             "the serial device went away (cable pulled or USB adapter removed); " <>
               "it is reopened when it is back"

    wait_until(fn -> not Serial.os_alive?(socat_pid(end_a)) end)
    wait_until(fn -> not Serial.os_alive?(socat_pid(end_b)) end)
    assert Transport.close(end_a) == :ok
  end

  test "when the controlling process dies, socat exits", ctx do
    test = self()

    {pid, monitor} =
      spawn_monitor(fn ->
        {:ok, conn} = Transport.connect("tty:#{ctx.a}")
        send(test, {:socat, socat_pid(conn)})
      end)

    assert_receive {:socat, os_pid}
    assert_receive {:DOWN, ^monitor, :process, ^pid, :normal}
    wait_until(fn -> not Serial.os_alive?(os_pid) end)
  end

  test "the line settings reach the device", ctx do
    {end_a, end_b} = open_both(ctx, "baud=4800&parity=odd&stop_bits=2")

    if stty = System.find_executable("stty") do
      {settings, 0} = System.cmd(stty, ["-F", ctx.a, "-a"])
      assert settings =~ "speed 4800 baud"
      assert settings =~ ~r/(^|\s)cstopb/
      assert settings =~ ~r/(^|\s)parodd/
      assert settings =~ ~r/(^|\s)-icanon/
      assert settings =~ ~r/(^|\s)-echo\s/
      # (A Linux pty always reports cs8 -parenb whatever it is told; a real UART keeps them.)
    end

    :ok = Transport.close(end_a)
    :ok = Transport.close(end_b)
  end

  test "flow control reaches the device: XON/XOFF, RTS/CTS, none", ctx do
    for {flow, expected} <- [
          {"xonxoff", [~r/(^|\s)ixon(\s|$)/, ~r/(^|\s)ixoff(\s|$)/, ~r/(^|\s)-crtscts/]},
          {"rtscts", [~r/(^|\s)-ixon/, ~r/(^|\s)-ixoff/, ~r/(^|\s)crtscts/]},
          {"none", [~r/(^|\s)-ixon/, ~r/(^|\s)-ixoff/, ~r/(^|\s)-crtscts/]}
        ] do
      {:ok, end_a} = Transport.connect("tty:#{ctx.a}?baud=4800&stop_bits=2&flow=#{flow}")
      # socat has configured the line once it relays: a byte through it proves that
      {:ok, end_b} = Transport.connect("tty:#{ctx.b}")
      :ok = Transport.send(end_a, "x")
      assert recv_exactly(end_b, 1) == "x"
      {settings, 0} = System.cmd("stty", ["-F", ctx.a, "-a"])
      assert settings =~ "speed 4800 baud"
      assert settings =~ ~r/(^|\s)cstopb/

      for pattern <- expected,
          do: assert(settings =~ pattern, "flow=#{flow}: #{inspect(pattern)} in #{settings}")

      :ok = Transport.close(end_a)
      :ok = Transport.close(end_b)
    end
  end

  test "a link whose tty went away says so and opens it again once it is back", ctx do
    {:ok, link} = Vws.Links.DNC.start_link(endpoint: "tty:#{ctx.a}?baud=4800", owner: self())
    assert_receive {:dnc, ^link, :connected}, 5_000

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        System.cmd("kill", [Integer.to_string(ctx.cable_pid)])
        assert_receive {:dnc, ^link, :disconnected}, 5_000
        # plugged in again where it was
        Vws.Test.PtyPair.start!(dir: ctx.dir)
        assert_receive {:dnc, ^link, :connected}, 10_000
      end)

    assert log =~ "the serial device went away (cable pulled or USB adapter removed)"
    GenServer.stop(link)
  end

  test "messages are classified per connection", ctx do
    {end_a, end_b} = open_both(ctx)
    port_a = end_a.handle.port

    assert Transport.handle_message(end_a, {port_a, {:exit_status, 0}}) == :closed

    assert Transport.handle_message(end_a, {port_a, {:exit_status, 1}}) ==
             {:error, %Vws.Links.Transport.Error{reason: {:socat_exit, 1}}}

    assert Transport.handle_message(end_a, {:EXIT, port_a, :normal}) == :closed
    assert Transport.handle_message(end_b, {port_a, {:data, "x"}}) == :unknown
    assert Transport.handle_message(end_a, {:tcp, port_a, "x"}) == :unknown
    :ok = Transport.close(end_a)
    :ok = Transport.close(end_b)
  end

  test "devices that cannot be opened are refused at connect", ctx do
    regular = Path.join(ctx.dir, "not-a-tty")
    File.write!(regular, "")

    assert Transport.connect("tty:#{ctx.dir}/missing") ==
             {:error, %Vws.Links.Transport.Error{reason: :enoent}}

    assert Transport.connect("tty:#{regular}") ==
             {:error, %Vws.Links.Transport.Error{reason: :not_a_tty}}

    assert Transport.connect("tty:#{ctx.a}", backend: :modem) ==
             {:error, %Vws.Links.Transport.Error{reason: {:unknown_backend, :modem}}}

    assert Transport.connect("tty:#{ctx.a}", socat: "/nonexistent/socat") ==
             {:error, %Vws.Links.Transport.Error{reason: :socat_not_found}}
  end

  test "without Circuits.UART, :auto means socat" do
    refute Code.ensure_loaded?(Circuits.UART)

    assert Serial.socat_args(Vws.Links.Endpoint.parse!("tty:/dev/ttyS0")) |> List.last() =~
             "FILE:/dev/ttyS0,"
  end

  doctest Vws.Links.Transport.Serial
end
