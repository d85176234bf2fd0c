defmodule Vws.Acceptance.HTTPHostileTest do
  # Issue 30's black-box check against a real `mix vws.serve` OS process: 1,100 abandoned MTConnect
  # streams from one address (each: the request without a token, the answer's head, close), then
  # `/current` from the same address answers within 15 s, and the node holds no connection left
  # over from them (none waits in CLOSE-WAIT for its stream's next part).
  use ExUnit.Case, async: true

  alias Vws.Test.{Acceptance, MTCClient}

  @moduletag :acceptance
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp head(port, path) do
    {:ok, s} = :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false], 10_000)
    :ok = :gen_tcp.send(s, "GET #{path} HTTP/1.1\r\nhost: x\r\n\r\n")
    :ok = :inet.setopts(s, packet: :http_bin)
    answer = :gen_tcp.recv(s, 0, 30_000)
    :gen_tcp.close(s)

    case answer do
      {:ok, {:http_response, _, status, _}} -> status
      other -> other
    end
  end

  # the node's TCP connections to `port` in CLOSE-WAIT (state 08 in /proc/net/tcp)
  defp close_wait(port) do
    hex = port |> Integer.to_string(16) |> String.pad_leading(4, "0")

    "/proc/net/tcp"
    |> File.read!()
    |> String.split("\n")
    |> Enum.count(fn line ->
      case String.split(line) do
        [_, local, _remote, "08" | _] -> String.ends_with?(local, ":" <> hex)
        _ -> false
      end
    end)
  end

  test "1,100 abandoned streams, then /current answers within 15 s and nothing waits in CLOSE-WAIT" do
    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "0", "--http-port", "0", "--time-scale", "20"],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)

    [_, http] =
      Acceptance.await(proc, ~r/Dashboard and MTConnect agent: http:\/\/127\.0\.0\.1:(\d+)\//)

    http = String.to_integer(http)
    assert {200, _, _} = MTCClient.get(http, "/current")

    # the issue's requests (now refused OUT_OF_RANGE at once) and streams that are served
    statuses =
      1..1_100
      |> Task.async_stream(
        fn i ->
          interval = if rem(i, 2) == 0, do: 2_147_483_646, else: 10_000
          head(http, "/current?interval=#{interval}")
        end,
        max_concurrency: 200,
        timeout: 60_000
      )
      |> Enum.map(fn {:ok, status} -> status end)
      |> Enum.frequencies()

    assert Map.get(statuses, 400, 0) > 0 and Map.get(statuses, 200, 0) > 0, inspect(statuses)

    parent = self()
    spawn_link(fn -> send(parent, {:current, MTCClient.get(http, "/current")}) end)
    assert_receive {:current, {200, "application/xml", body}}, 15_000
    assert body =~ "MTConnectStreams"

    # the 10 s streams ended with their clients
    assert Vws.Test.Eventually.eventually(fn -> close_wait(http) == 0 end, 5_000)
  end
end
