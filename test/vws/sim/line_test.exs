defmodule Vws.Sim.LineTest do
  use ExUnit.Case, async: true

  import Vws.TransportHelpers

  alias Vws.Sim.Line
  alias Vws.Sim.Line.Faults
  alias Vws.Links.Transport

  doctest Line

  defp unique(prefix), do: "#{prefix}-#{System.unique_integer([:positive])}"

  # A target listener, a line in front of it, a client through the line and the target's end.
  defp through(kind, opts \\ []) do
    {target_ep, listen_ep} =
      case kind do
        :tcp -> {"tcp://127.0.0.1:0", "tcp://127.0.0.1:0"}
        :loopback -> {"loopback:#{unique("target")}", "loopback:#{unique("line")}"}
      end

    {:ok, target} = Transport.listen(target_ep)
    target_ep = Transport.listener_endpoint(target)

    spec = {Line, Keyword.merge([listen: listen_ep, target: target_ep], opts)}
    line = start_supervised!(Supervisor.child_spec(spec, id: make_ref(), restart: :temporary))

    {:ok, client} = Transport.connect(Line.endpoint(line))
    {:ok, server} = Transport.accept(target, 5_000)
    %{line: line, client: client, server: server, target: target}
  end

  defp pattern(size),
    do: for(i <- 0..(size - 1), into: <<>>, do: <<rem(i * 7 + div(i, 251), 256)>>)

  # Everything `conn` receives until it is closed (or `timeout` ms pass without a message).
  defp recv_until_closed(conn, timeout \\ 5_000, acc \\ []) do
    :ok = Transport.activate(conn)

    case next(conn, timeout) do
      {:data, data} -> recv_until_closed(conn, timeout, [acc | data])
      other -> {IO.iodata_to_binary(acc), other}
    end
  end

  describe "relay without faults" do
    for kind <- [:tcp, :loopback] do
      test "1 MB each way arrives intact (#{kind})" do
        %{client: client, server: server, line: line} = through(unquote(kind))
        up = pattern(1_048_576)
        down = :binary.copy(<<0, 0xFF, ?\n, ?\r>>, 262_144)

        sender = Task.async(fn -> Transport.send(server, down) end)
        :ok = Transport.send(client, up)
        assert recv_exactly(server, byte_size(up), 20_000) == up
        assert recv_exactly(client, byte_size(down), 20_000) == down
        assert Task.await(sender) == :ok

        info = Line.info(line)
        assert info.to_target.bytes_in == 1_048_576
        assert info.to_target.bytes_out == 1_048_576
        assert info.to_client.bytes_out == 1_048_576
        assert info.to_target.bits_flipped == 0
        assert info.open == 1
      end
    end

    test "a close is passed on after the bytes sent before it" do
      %{client: client, server: server, line: line} = through(:loopback, faults: [delay: 30])
      :ok = Transport.send(client, "last words")
      :ok = Transport.close(client)
      assert recv_until_closed(server) == {"last words", :closed}
      wait_until(fn -> Line.info(line).open == 0 end)
      assert Line.info(line).closes == 1
    end

    # Over loopback: over TCP the chatter into the closed client draws an RST, and Linux discards
    # the line's unread receive data on a reset — a race of the kernel, not of the line.
    test "… also while the other direction is still sending to the end that closed" do
      %{client: client, server: server} = through(:loopback, to_target: [delay: 50])

      chatter =
        Task.async(fn ->
          Enum.reduce_while(1..1_000, :ok, fn _, _ ->
            case Transport.send(server, :binary.copy("c", 4_096)) do
              :ok -> Process.sleep(1) && {:cont, :ok}
              error -> {:halt, error}
            end
          end)
        end)

      Process.sleep(20)
      :ok = Transport.send(client, "bye")
      :ok = Transport.close(client)
      # the server (busy sending) sees "bye", then the close
      assert {"bye", end_} = recv_until_closed(server)
      assert end_ in [:closed, {:error, %Vws.Links.Transport.Error{reason: :econnreset}}]
      Task.shutdown(chatter, :brutal_kill)
    end
  end

  describe "faults through the process" do
    test "the damage is the pure core's, seeded {seed, connection number, direction}" do
      opts = [ber: 1.0e-2, drop: 1.0e-2]
      %{client: client, server: server} = through(:loopback, seed: 77, to_target: opts)
      bytes = pattern(20_000)

      # sent in uneven pieces: the damage does not depend on the cut
      for piece <- Vws.Codecs.WC.Generators.chunks(bytes, [1, 700, 33, 4096, 5]),
          do: :ok = Transport.send(client, piece)

      {expected, _} = Faults.apply(bytes, Faults.new([seed: {77, 0, :to_target}] ++ opts))
      assert expected != bytes
      assert recv_exactly(server, byte_size(expected)) == expected

      # and the other direction is clean
      :ok = Transport.send(server, "back")
      assert recv_exactly(client, 4) == "back"
    end

    test "the same seed gives the same damage, another seed other damage" do
      out = fn seed ->
        %{client: client, server: server} = through(:tcp, seed: seed, faults: [ber: 1.0e-2])
        :ok = Transport.send(client, pattern(5_000))
        recv_exactly(server, 5_000)
      end

      assert out.(3) == out.(3)
      assert out.(3) != out.(4)
    end

    test "faults change at run time, per direction or both" do
      %{client: client, server: server, line: line} = through(:loopback)
      :ok = Transport.send(client, "abc")
      assert recv_exactly(server, 3) == "abc"

      :ok = Line.set_faults(line, :to_target, ber: 1.0)
      :ok = Transport.send(client, "abc")
      assert recv_exactly(server, 3) == <<0x9E, 0x9D, 0x9C>>
      :ok = Transport.send(server, "abc")
      assert recv_exactly(client, 3) == "abc"

      :ok = Line.set_faults(line, :both, ber: 0.0, drop: 1.0)
      :ok = Transport.send(client, "lost")
      :ok = Transport.send(server, "lost")
      :ok = Line.set_faults(line, :both, drop: 0.0)
      :ok = Transport.send(client, "kept")
      :ok = Transport.send(server, "kept")
      assert recv_exactly(server, 4) == "kept"
      assert recv_exactly(client, 4) == "kept"

      info = Line.info(line)
      assert info.to_target.bytes_dropped == 4
      assert info.to_client.bytes_dropped == 4
      assert info.to_target.bits_flipped == 24
      assert info.faults.to_target[:drop] == 0.0
      assert info.faults.to_target[:ber] == 0.0

      assert_raise ArgumentError, fn -> Line.set_faults(line, :both, ber: 2) end
      assert_raise ArgumentError, fn -> Line.set_faults(line, :both, bogus: 1) end
    end
  end

  describe "pacing" do
    test "960 bytes at 9600 Bd take at least a second, and never come faster than the line" do
      %{client: client, server: server} = through(:tcp, to_target: [baud: 9600])
      t0 = System.monotonic_time(:microsecond)
      :ok = Transport.send(client, :binary.copy("U", 960))
      arrivals = paced_arrivals(server, 960, t0, [])
      elapsed = System.monotonic_time(:microsecond) - t0
      assert elapsed >= 995_000

      # at every arrival, no more bytes than 9600 Bd could have carried since the send
      for {total, at} <- arrivals, do: assert(total <= div(at * 960, 1_000_000) + 1)
      assert length(arrivals) > 5
    end

    test "the other direction is not paced" do
      %{client: client, server: server} = through(:loopback, to_target: [baud: 300])
      :ok = Transport.send(server, :binary.copy("x", 10_000))
      assert byte_size(recv_exactly(client, 10_000, 5_000)) == 10_000
    end
  end

  defp paced_arrivals(_conn, remaining, _t0, acc) when remaining <= 0, do: Enum.reverse(acc)

  defp paced_arrivals(conn, remaining, t0, acc) do
    :ok = Transport.activate(conn)
    {:data, data} = next(conn, 5_000)
    at = System.monotonic_time(:microsecond) - t0
    total = if acc == [], do: 0, else: elem(hd(acc), 0)
    paced_arrivals(conn, remaining - byte_size(data), t0, [{total + byte_size(data), at} | acc])
  end

  describe "disconnects" do
    test "after N bytes: the N bytes arrive, then both ends see the link closed (loopback)" do
      %{client: client, server: server, line: line} =
        through(:loopback, to_target: [disconnect_after: 100])

      bytes = pattern(300)
      :ok = Transport.send(client, bytes)
      assert recv_until_closed(server) == {binary_part(bytes, 0, 100), :closed}
      assert_closed(client)
      wait_until(fn -> Line.info(line).open == 0 end)
      assert Line.info(line).disconnects == 1
      assert Line.info(line).to_target.bytes_out == 100
    end

    test "after N bytes, paced: the cut waits for the N-th byte to be out (tcp)" do
      %{client: client, server: server} =
        through(:tcp, to_client: [disconnect_after: 50, baud: 19_200])

      :ok = Transport.send(server, pattern(500))
      assert {received, end_} = recv_until_closed(client)
      assert received == binary_part(pattern(500), 0, 50)
      assert end_ in [:closed, {:error, %Vws.Links.Transport.Error{reason: :econnreset}}]
      :ok = Transport.activate(server)
      assert next(server) in [:closed, {:error, %Vws.Links.Transport.Error{reason: :econnreset}}]
    end

    test "on command: both ends see the link closed; new connections are relayed" do
      %{client: client, server: server, line: line, target: target} = through(:loopback)
      :ok = Transport.send(client, "hello")
      assert recv_exactly(server, 5) == "hello"
      :ok = Line.disconnect(line)
      assert_closed(client)
      assert_closed(server)
      assert Line.info(line).disconnects == 1

      {:ok, client2} = Transport.connect(Line.endpoint(line))
      {:ok, server2} = Transport.accept(target, 5_000)
      :ok = Transport.send(client2, "again")
      assert recv_exactly(server2, 5) == "again"
      assert Line.info(line).connections == 2
    end

    test "at random, with a rate per second" do
      %{client: client, server: server, line: line} =
        through(:loopback, faults: [disconnect_rate: 20.0])

      # 40 cuts a second on average: that none comes within 5 s has probability e^-200
      assert_closed(client, 5_000)
      assert_closed(server, 5_000)
      assert Line.info(line).disconnects == 1
    end

    test "a target that cannot be reached closes the accepted connection" do
      line =
        start_supervised!(
          {Line,
           listen: "loopback:#{unique("line")}",
           target: "loopback:#{unique("nobody")}",
           connect_timeout: 50}
        )

      {:ok, client} = Transport.connect(Line.endpoint(line))
      assert_closed(client)
      wait_until(fn -> Line.info(line).connect_failures == 1 end)
    end

    test "stopping the line closes its connections" do
      %{client: client, server: server, line: line} = through(:tcp)
      :ok = Line.stop(line)
      assert_closed(client)
      assert_closed(server)
    end
  end

  describe "bounded" do
    test "a fast sender on a slow line is held back: the line holds at most max_queue + one delivery" do
      max_queue = 4_096

      %{client: client, server: server, line: line} =
        through(:tcp, max_queue: max_queue, to_target: [baud: 9600])

      chunk = :binary.copy("z", 65_536)

      sender =
        Task.async(fn ->
          Enum.reduce_while(1..256, 0, fn _, sent ->
            case Transport.send(client, chunk) do
              :ok -> {:cont, sent + byte_size(chunk)}
              {:error, _} -> {:halt, sent}
            end
          end)
        end)

      samples =
        for _ <- 1..10 do
          Process.sleep(50)
          Line.info(line).to_target
        end

      for s <- samples do
        assert s.queued <= max_queue + 65_536
        assert s.bytes_in - s.bytes_out <= max_queue + 65_536
        # held back, not dropped: a TCP source is armed for one delivery at a time
        assert s.overruns == 0
      end

      # 16 MB offered; well under a second of 960 bytes a second went through
      refute Task.yield(sender, 0)
      assert Enum.at(samples, -1).bytes_out < 5_000
      Transport.close(server)
      Line.disconnect(line)
      Task.shutdown(sender, :brutal_kill)
    end
  end
end
