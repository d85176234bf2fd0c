defmodule Vws.Links.Transport.RFC2217Test do
  # Against ser2net (Debian), an RFC 2217 server we did not write, in front of a pty pair.
  use ExUnit.Case, async: true

  import Vws.TransportHelpers

  alias Vws.Links.Transport
  alias Vws.Links.Transport.RFC2217

  @moduletag :tty

  setup do
    pair = Vws.Test.PtyPair.start!()
    server = Vws.Test.Ser2net.start!(pair.a, pair.dir)
    Map.merge(pair, %{server: server, url: "rfc2217://127.0.0.1:#{server.port}"})
  end

  defp stty(path) do
    {settings, 0} = System.cmd("stty", ["-F", path, "-a"])
    settings
  end

  test "the settings the CEC asks for are the ones the pty gets; data (every byte) flows both ways",
       ctx do
    {:ok, conn} = Transport.connect("#{ctx.url}?baud=4800&stop_bits=2&parity=even&data_bits=7")
    {:ok, far} = Transport.connect("tty:#{ctx.b}")

    # what ser2net answered: the values asked
    state = RFC2217.line_state(conn)

    assert state.settings == %{
             baud: 4800,
             data_size: 7,
             parity: :even,
             stop_size: 2,
             control: :none
           }

    settings = stty(ctx.a)
    assert settings =~ "speed 4800 baud"
    assert settings =~ ~r/(^|\s)cstopb/

    # (a Linux pty forces cs8 -parenb whatever it is told: DESIGN.md; the server's answers say them)

    every_byte = Enum.into(0..255, <<>>, &<<&1>>)
    :ok = Transport.send(conn, [every_byte, <<255, 255>>])
    assert recv_exactly(far, 258) == every_byte <> <<255, 255>>
    :ok = Transport.send(far, every_byte)
    assert recv_exactly(conn, 256) == every_byte
    :ok = Transport.close(conn)
    :ok = Transport.close(far)
  end

  test "flow control is set on the server's port: XON/XOFF, RTS/CTS", ctx do
    for {flow, expected} <- [
          {"xonxoff", [~r/(^|\s)ixon(\s|$)/, ~r/(^|\s)-crtscts/]},
          {"rtscts", [~r/(^|\s)-ixon/, ~r/(^|\s)crtscts/]}
        ] do
      {:ok, conn} = Transport.connect("#{ctx.url}?baud=9600&flow=#{flow}")
      assert RFC2217.line_state(conn).settings.control == String.to_atom(flow)
      settings = stty(ctx.a)
      for pattern <- expected, do: assert(settings =~ pattern, "#{flow}: #{settings}")
      :ok = Transport.close(conn)
    end
  end

  test "a server that is not RFC 2217 (a plain TCP port) ends the connect in words" do
    {:ok, listener} = :gen_tcp.listen(0, [:binary, active: false, ip: {127, 0, 0, 1}])
    {:ok, port} = :inet.port(listener)

    spawn_link(fn ->
      {:ok, s} = :gen_tcp.accept(listener)
      # a telnet server without the option: it refuses it
      :gen_tcp.send(s, <<255, 254, 44>>)
      Process.sleep(5_000)
    end)

    assert {:error, %Transport.Error{reason: :com_port_refused} = e} =
             Transport.connect("rfc2217://127.0.0.1:#{port}")

    assert Exception.message(e) =~ "the terminal server refused RFC 2217"
  end

  test "a server that answers another value: refused in words" do
    {:ok, listener} = :gen_tcp.listen(0, [:binary, active: false, ip: {127, 0, 0, 1}])
    {:ok, port} = :inet.port(listener)

    spawn_link(fn ->
      {:ok, s} = :gen_tcp.accept(listener)
      :gen_tcp.send(s, <<255, 253, 44>>)
      # every setting answered as asked, but 8 data bits whatever was asked
      :gen_tcp.send(s, <<255, 250, 44, 101, 0, 0, 0x25, 0x80, 255, 240>>)
      :gen_tcp.send(s, <<255, 250, 44, 102, 8, 255, 240>>)
      :gen_tcp.send(s, <<255, 250, 44, 103, 1, 255, 240, 255, 250, 44, 104, 1, 255, 240>>)
      :gen_tcp.send(s, <<255, 250, 44, 105, 1, 255, 240>>)
      Process.sleep(5_000)
    end)

    assert {:error, %Transport.Error{reason: {:setting_refused, :data_size, 7, 8}} = e} =
             Transport.connect("rfc2217://127.0.0.1:#{port}?data_bits=7")

    assert Exception.message(e) ==
             "the terminal server would not set data_size to 7 (it answered 8): its port cannot do that"
  end

  test "line-state notifications are followed: errors said and counted, modem lines kept" do
    {:ok, listener} = :gen_tcp.listen(0, [:binary, active: false, ip: {127, 0, 0, 1}])
    {:ok, port} = :inet.port(listener)
    test = self()

    spawn_link(fn ->
      {:ok, s} = :gen_tcp.accept(listener)
      :gen_tcp.send(s, <<255, 253, 44>>)
      :gen_tcp.send(s, <<255, 250, 44, 101, 0, 0, 0x25, 0x80, 255, 240>>)
      :gen_tcp.send(s, <<255, 250, 44, 102, 8, 255, 240, 255, 250, 44, 103, 1, 255, 240>>)
      :gen_tcp.send(s, <<255, 250, 44, 104, 1, 255, 240, 255, 250, 44, 105, 1, 255, 240>>)
      receive do: (:go -> :ok)
      # an overrun and a parity error, then carrier and CTS on; data around them
      :gen_tcp.send(s, <<"ab", 255, 250, 44, 106, 0x06, 255, 240, 255, 250, 44, 107, 0x90>>)
      :gen_tcp.send(s, <<255, 240, "c">>)
      send(test, :sent)
      Process.sleep(5_000)
    end)
    |> then(fn pid -> Process.put(:server, pid) end)

    {:ok, conn} = Transport.connect("rfc2217://127.0.0.1:#{port}")

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        send(Process.get(:server), :go)
        assert_receive :sent
        assert recv_exactly(conn, 3) == "abc"
      end)

    assert log =~ "the serial line reports overrun, parity error"
    state = RFC2217.line_state(conn)
    assert state.line_errors == 2
    assert state.modemstate == 0x90
    :ok = Transport.close(conn)
  end

  test "a server that never answers: a bounded wait" do
    {:ok, listener} = :gen_tcp.listen(0, [:binary, active: false, ip: {127, 0, 0, 1}])
    {:ok, port} = :inet.port(listener)

    spawn_link(fn ->
      {:ok, _s} = :gen_tcp.accept(listener)
      Process.sleep(5_000)
    end)

    assert {:error, %Transport.Error{reason: :negotiation_timeout}} =
             Transport.connect("rfc2217://127.0.0.1:#{port}", timeout: 300)
  end
end
