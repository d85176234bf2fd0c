defmodule Vws.Links.DDCMPTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.DDCMP
  alias Vws.Test.DDCMPRelay, as: Relay

  doctest DDCMP

  # Two links, A and B, joined through a relay (which can lose and damage chunks of bytes).
  defp pair(relay_opts, link_opts, b_opts \\ []) do
    relay = start_supervised!({Relay, relay_opts}, id: :relay)
    {a_end, b_end} = Relay.endpoints(relay)

    a = start_supervised!({DDCMP, [endpoint: a_end, owner: self()] ++ link_opts}, id: :a)

    b =
      start_supervised!(
        {DDCMP, [endpoint: b_end, owner: self()] ++ link_opts ++ b_opts},
        id: :b
      )

    assert_receive {:ddcmp, ^a, :up}, 10_000
    assert_receive {:ddcmp, ^b, :up}, 10_000
    {relay, a, b}
  end

  # Every message each link receives, in order, until `count` have arrived at each.
  defp collect(a, b, count, timeout) do
    collect(a, b, count, %{a => [], b => []}, System.monotonic_time(:millisecond) + timeout)
  end

  defp collect(a, b, count, got, deadline) do
    if length(got[a]) >= count and length(got[b]) >= count do
      %{a: Enum.reverse(got[a]), b: Enum.reverse(got[b])}
    else
      wait = max(deadline - System.monotonic_time(:millisecond), 0)

      receive do
        {:ddcmp, link, {:data, bytes}} when link in [a, b] ->
          collect(a, b, count, Map.update!(got, link, &[bytes | &1]), deadline)

        {:ddcmp, link, other} when link in [a, b] ->
          flunk("unexpected #{inspect(other)} from #{if link == a, do: "A", else: "B"}")
      after
        wait ->
          flunk("timed out: A got #{length(got[a])}, B got #{length(got[b])} of #{count}")
      end
    end
  end

  defp messages(seed, count, alphabet) do
    :rand.seed(:exsss, {seed, 2, 3})

    for i <- 1..count do
      size = :rand.uniform(300) - 1
      body = for _ <- 1..size//1, into: <<>>, do: <<Enum.random(alphabet)>>
      <<i::32, body::binary>>
    end
  end

  defp send_all(link, messages) do
    Task.async(fn -> for m <- messages, do: :ok = DDCMP.send_data(link, m) end)
  end

  test "1000 messages of random sizes each way: all delivered once, in order, window kept" do
    window = 5
    {relay, a, b} = pair([], window: window, rep_timeout: 1000)
    to_b = messages(11, 1000, 0..255)
    to_a = messages(12, 1000, 0..255)
    tasks = [send_all(a, to_b), send_all(b, to_a)]

    got = collect(a, b, 1000, 30_000)
    Task.await_many(tasks, 30_000)
    assert got.b == to_b
    assert got.a == to_a

    # Sequence numbers wrapped round 256 several times.
    assert %{state: :running, counters: %{sent: 1000, received: 1000}} = DDCMP.info(a)
    assert %{counters: %{sent: 1000, received: 1000}} = DDCMP.info(b)

    %{max_outstanding: seen} = Relay.stats(relay)
    assert seen.a <= window and seen.b <= window
    refute_received {:ddcmp, _, _}
  end

  test "restart/1 on one side: the other side sees :peer_restarted, both come up again" do
    {_relay, a, b} = pair([], start_timeout: 100)
    :ok = DDCMP.send_data(a, "before")
    assert_receive {:ddcmp, ^b, {:data, "before"}}, 5000

    :ok = DDCMP.restart(b)
    assert_receive {:ddcmp, ^b, {:down, :restart}}, 5000
    assert_receive {:ddcmp, ^a, :peer_restarted}, 5000
    assert_receive {:ddcmp, ^a, :up}, 5000
    assert_receive {:ddcmp, ^b, :up}, 5000

    :ok = DDCMP.send_data(b, "after")
    assert_receive {:ddcmp, ^a, {:data, "after"}}, 5000
  end

  test "a passive side (a simulated VAL II) starts up with an active one" do
    {_relay, a, b} = pair([], [start_timeout: 100], role: :passive)
    :ok = DDCMP.send_data(b, "prompt")
    assert_receive {:ddcmp, ^a, {:data, "prompt"}}, 5000
  end

  test "cross-over start: both sides active" do
    {_relay, a, b} = pair([], start_timeout: 100)
    assert %{state: :running} = DDCMP.info(a)
    assert %{state: :running} = DDCMP.info(b)
  end

  # Printable text, as VAL messages are: a damaged header then never makes the decoder find a
  # false class byte inside a message body.
  @printable Enum.to_list(?\s..?~)

  defp lossy_line_property do
    :proper.forall(
      {:proper_types.integer(1, 1_000_000), :proper_types.integer(1, 8),
       :proper_types.integer(0, 12), :proper_types.integer(0, 12)},
      fn {seed, window, drop, corrupt} ->
        relay_opts = [seed: seed, drop: drop / 100, corrupt: corrupt / 100]
        link_opts = [window: window, rep_timeout: 25, start_timeout: 25, max_failures: 1_000_000]

        try do
          {_relay, a, b} = pair(relay_opts, link_opts)
          to_b = messages(seed, 120, @printable)
          to_a = messages(seed + 1, 120, @printable)
          tasks = [send_all(a, to_b), send_all(b, to_a)]
          got = collect(a, b, 120, 60_000)
          Task.await_many(tasks, 10_000)
          refute_receive {:ddcmp, _, {:data, _}}, 100
          got.b == to_b and got.a == to_a
        after
          for id <- [:a, :b, :relay], do: stop_supervised(id)
          flush()
        end
      end
    )
  end

  defp flush do
    receive do
      _ -> flush()
    after
      0 -> :ok
    end
  end

  @tag timeout: 300_000
  test "send_data with hold: false is refused unless the link is RUNNING; the default holds it" do
    {:ok, link} =
      DDCMP.start_link(
        endpoint: "loopback:nobody-#{System.unique_integer([:positive])}",
        owner: self()
      )

    assert DDCMP.send_data(link, "DO MOVE SAFE", hold: false) == {:error, :not_running}
    assert DDCMP.send_data(link, "held") == :ok
    assert DDCMP.info(link).state != :running
  end

  test "a link that has ended refuses send_data with hold: false; it does not exit the caller" do
    Process.flag(:trap_exit, true)

    {:ok, link} =
      DDCMP.start_link(
        endpoint: "loopback:nobody-#{System.unique_integer([:positive])}",
        owner: self()
      )

    :ok = DDCMP.stop(link)
    # its end reaches this (trapping) owner as a message, after the calls below
    assert DDCMP.send_data(link, "DO MOVE SAFE", hold: false) == {:error, :not_running}
    assert_receive {:EXIT, ^link, _}
  end

  test "send_data takes hold: and nothing else (the session: option is gone)" do
    {_relay, a, _b} = pair([], [])
    assert_raise Vws.Options.Error, ~r/session/, fn -> DDCMP.send_data(a, "first", session: 1) end
    assert_raise Vws.Options.Error, ~r/hold/, fn -> DDCMP.send_data(a, "first", hold: :no) end
  end

  test "lossy line (PropEr over seeds, windows, loss and damage rates): each message once, in order" do
    assert_property(lossy_line_property(), 4)
  end

  describe "options" do
    test "exactly one of :endpoint and :conn" do
      assert_raise ArgumentError, fn -> DDCMP.start_link(owner: self()) end
    end

    test "invalid values are refused, naming the option" do
      for {key, _} = bad <- [
            window: 0,
            window: 256,
            role: :master,
            max_data: 20_000,
            rep_timeout: 0,
            backoff: {10, 5},
            endpoint: "ftp://x"
          ] do
        error =
          assert_raise Vws.Options.Error, fn ->
            DDCMP.start_link(Keyword.merge([endpoint: "loopback:x"], [bad]))
          end

        assert error.key == key and error.reason == :invalid
      end
    end

    test "an unknown option is refused at start" do
      error =
        assert_raise Vws.Options.Error, fn ->
          DDCMP.start_link(endpoint: "loopback:x", windw: 3)
        end

      assert Exception.message(error) =~ "unknown DDCMP option :windw"
    end

    test "child_spec/1 takes the name as id" do
      assert %{id: :robot_link, start: {DDCMP, :start_link, [_]}} =
               DDCMP.child_spec(name: :robot_link, endpoint: "loopback:x")
    end
  end
end
