defmodule Vws.Ops.MTConnect.RequestsTest do
  # The request parameters real MTConnect clients use, over real HTTP (Vws.Ops.Web on a free port):
  # path=, at=, from/count/to, interval/heartbeat streaming, /assets, JSON, and the error
  # documents for everything the agent cannot serve. Every XML document is validated.
  use ExUnit.Case, async: true

  # validates against the official schemas (test/test_helper.exs excludes it without them)
  @moduletag :mtconnect_schemas

  alias Vws.CEC.Mailbox
  alias Vws.Test.{JSONDecode, MTCClient, XMLLint}

  import MTCClient, only: [observations: 1, header: 2]

  setup do
    %{ws: ws} = Vws.Test.Workstation.start()
    opts = [port: 0, workstations: fn -> [ws] end, interval: 60_000]
    pid = start_supervised!({Vws.Ops.Web, opts ++ [buffer_size: 64, checkpoint_frequency: 10]})
    "http://127.0.0.1:" <> rest = Vws.Ops.Web.url(pid)
    port = rest |> String.trim_trailing("/") |> String.to_integer()
    %{ws: ws, id: "ws_" <> ws, port: port}
  end

  defp get!(port, path, kind, status \\ 200) do
    {^status, "application/xml", body} = MTCClient.get(port, path)
    XMLLint.validate!(body, kind)
  end

  # for loops: the same answer, not validated each time (xmllint with the 2.5 Streams schema
  # costs about half a second); the tests validate one of each kind
  defp raw!(port, path) do
    {200, "application/xml", body} = MTCClient.get(port, path)
    body
  end

  defp error!(port, path, code, status \\ 400) do
    text = get!(port, path, :error, status)
    assert text =~ ~s(errorCode="#{code}"), text
    text
  end

  defp ids(text), do: text |> observations() |> Enum.map(&elem(&1, 1)) |> Enum.uniq()

  describe "path=" do
    test "by type, name, id, component by name, predicates, union", %{port: port, id: id, ws: ws} do
      q = &URI.encode_www_form/1

      text = get!(port, "/current?path=" <> q.(~s(//DataItem[@type="EXECUTION"])), :streams)
      assert Enum.sort(ids(text)) == Enum.sort(["#{id}_vmc_path_exec", "#{id}_robot_path_exec"])

      text = get!(port, "/current?path=" <> q.(~s(//DataItem[@name='jaw_width'])), :streams)
      assert ids(text) == ["#{id}_vise_jaw"]

      text = get!(port, "/current?path=" <> q.(~s(//DataItem[@id="#{id}_tray2_state"])), :streams)
      assert ids(text) == ["#{id}_tray2_state"]

      # a component by name: every data item in it and below it
      text = get!(port, "/current?path=" <> q.(~s(//*[@name="vise"])), :streams)
      assert Enum.all?(ids(text), &String.starts_with?(&1, "#{id}_vise_"))
      assert "#{id}_vise_force" in ids(text) and "#{id}_vise_system" in ids(text)

      # a component by type, then a predicate with and, and a union
      text = get!(port, "/current?path=" <> q.("//Lock"), :streams)
      assert Enum.sort(ids(text)) == ["#{id}_tray1_state", "#{id}_tray2_state"]

      path =
        ~s(//Controller[@name="robot"]//DataItem[@category="SAMPLE" and @type="ANGLE"]|//Clamp//DataItem[@type="LOCK_STATE"])

      text = get!(port, "/current?path=" <> q.(path), :streams)
      assert length(ids(text)) == 7
      assert "#{id}_pallet_state" in ids(text) and "#{id}_robot_j6_angle" in ids(text)

      # the device's own path and the namespace prefix clients write
      text = get!(port, "/#{ws}/current?path=" <> q.(~s(//m:Devices/m:Device//m:Chuck)), :streams)
      assert "#{id}_vise_state" in ids(text)

      # sample filters the same way
      Mailbox.put_device(ws, 10, "PALLET CLAMPED")
      text = get!(port, "/sample?count=50&path=" <> q.("//Clamp"), :streams)
      assert ids(text) != [] and Enum.all?(ids(text), &String.starts_with?(&1, "#{id}_pallet_"))
    end

    test "a path that is not the supported XPath, or matches nothing, is INVALID_PATH", %{
      port: port
    } do
      q = &URI.encode_www_form/1
      error!(port, "/current?path=" <> q.("//DataItem[position()=1]"), "INVALID_PATH")
      error!(port, "/sample?path=" <> q.(~s(//DataItem[@type="NOPE"])), "INVALID_PATH")
      error!(port, "/current?path=" <> q.("//["), "INVALID_PATH")
      error!(port, "/current?path=", "INVALID_PATH")
    end
  end

  test "at=: the state at that sequence, from checkpoints, also after the buffer turned over",
       %{port: port, ws: ws} do
    # snapshots of /current taken as the changes come, then asked again with at=
    snapshots =
      for i <- 1..30 do
        Mailbox.put_device(
          ws,
          10,
          if(rem(i, 2) == 0, do: "PALLET CLAMPED", else: "PALLET NOT CLAMPED")
        )

        Mailbox.put_device(
          ws,
          4,
          "TRAY #1 #{if rem(i, 3) == 0, do: "", else: "NOT "}IN POSITION TRAY #2 IN POSITION"
        )

        text = raw!(port, "/current")
        {header(text, "nextSequence") - 1, Enum.sort(observations(text))}
      end

    first = header(get!(port, "/current", :streams), "firstSequence")
    assert first > 1, "the buffer (64) has turned over"

    get!(port, "/current?at=#{first}", :streams)

    for {at, expected} <- snapshots, at >= first do
      text = raw!(port, "/current?at=#{at}")
      assert Enum.sort(observations(text)) == expected, "at=#{at}"
    end

    last = header(get!(port, "/current", :streams), "lastSequence")
    error!(port, "/current?at=#{first - 1}", "OUT_OF_RANGE")
    error!(port, "/current?at=#{last + 1}", "OUT_OF_RANGE")
    error!(port, "/current?at=x", "INVALID_REQUEST")
    error!(port, "/current?at=3&interval=100", "INVALID_REQUEST")
  end

  test "from, count, to: pages without gaps or duplicates; negative count; ranges", %{
    port: port,
    ws: ws
  } do
    for i <- 1..10,
        do:
          Mailbox.put_device(
            ws,
            10,
            if(rem(i, 2) == 0, do: "PALLET CLAMPED", else: "PALLET NOT CLAMPED")
          )

    text = get!(port, "/current", :streams)
    {first, next} = {header(text, "firstSequence"), header(text, "nextSequence")}

    # paging with count=7 from firstSequence covers first..next-1 exactly once
    seqs =
      Stream.unfold(first, fn
        ^next ->
          nil

        from ->
          page = raw!(port, "/sample?from=#{from}&count=7")
          {Enum.map(observations(page), &elem(&1, 2)), header(page, "nextSequence")}
      end)
      |> Enum.concat()
      |> Enum.sort()

    assert seqs == Enum.to_list(first..(next - 1))

    # to: at most up to `to`, nextSequence just after it
    page = get!(port, "/sample?from=#{first}&to=#{first + 4}&count=50", :streams)

    assert observations(page) |> Enum.map(&elem(&1, 2)) |> Enum.sort() ==
             Enum.to_list(first..(first + 4))

    assert header(page, "nextSequence") == first + 5

    # a negative count: the last ones
    page = get!(port, "/sample?count=-3", :streams)

    assert observations(page) |> Enum.map(&elem(&1, 2)) |> Enum.sort() == [
             next - 3,
             next - 2,
             next - 1
           ]

    error!(port, "/sample?from=#{first}&to=#{first}", "OUT_OF_RANGE")
    error!(port, "/sample?to=#{next + 1}", "OUT_OF_RANGE")
    error!(port, "/sample?count=0", "OUT_OF_RANGE")
    error!(port, "/sample?count=65", "OUT_OF_RANGE")
    error!(port, "/sample?from=#{first - 1}", "OUT_OF_RANGE")
    error!(port, "/sample?to=#{first + 2}&interval=10", "INVALID_REQUEST")
    error!(port, "/sample?heartbeat=100", "INVALID_REQUEST")
    error!(port, "/sample?interval=-1", "OUT_OF_RANGE")
    error!(port, "/sample?interval=10&heartbeat=0", "OUT_OF_RANGE")
    error!(port, "/sample?interval=10&heartbeat=99999999999", "OUT_OF_RANGE")
    error!(port, "/current?interval=99999999999", "OUT_OF_RANGE")
  end

  test "interval + heartbeat: a multipart/x-mixed-replace stream over TCP, with heartbeats",
       %{port: port, ws: ws, id: id} do
    {ref, pid, head} = MTCClient.stream(port, "/sample?interval=0&heartbeat=300&count=50")
    assert head.status == 200
    assert head.headers["content-type"] =~ ~r{^multipart/x-mixed-replace;boundary=\w+}
    assert head.headers["transfer-encoding"] == "chunked"

    assert_receive {:mtc_part, ^ref, first}, 5_000
    first = XMLLint.validate!(first, :streams)
    next = header(first, "nextSequence")

    # nothing happens: heartbeats, each an empty document that keeps nextSequence
    assert_receive {:mtc_part, ^ref, beat}, 5_000
    beat = XMLLint.validate!(beat, :streams)
    assert observations(beat) == []
    assert header(beat, "nextSequence") == next

    # a change: the next part carries it, from exactly where the last part ended
    Mailbox.put_device(ws, 10, "PALLET CLAMPED")
    part = await_part_with(ref, "#{id}_pallet_state")
    seqs = part |> observations() |> Enum.map(&elem(&1, 2)) |> Enum.sort()
    assert hd(seqs) == next
    assert seqs == Enum.to_list(next..(header(part, "nextSequence") - 1))

    MTCClient.stop(pid)

    # current every interval ms
    {ref, pid, _head} = MTCClient.stream(port, "/current?interval=50")
    assert_receive {:mtc_part, ^ref, a}, 5_000
    assert_receive {:mtc_part, ^ref, b}, 5_000
    assert XMLLint.validate!(a, :streams) =~ "#{id}_avail"
    assert XMLLint.validate!(b, :streams) =~ "#{id}_avail"
    MTCClient.stop(pid)

    # a stream that cannot start is an ordinary error answer
    {_ref, _pid, head} = MTCClient.stream(port, "/sample?interval=10&from=999999")
    assert head.status == 400
  end

  defp await_part_with(ref, item) do
    receive do
      {:mtc_part, ^ref, doc} ->
        doc = XMLLint.validate!(doc, :streams)
        if doc =~ item, do: doc, else: await_part_with(ref, item)
    after
      5_000 -> flunk("no part with #{item}")
    end
  end

  test "/assets: an empty but valid MTConnectAssets document", %{port: port, ws: ws} do
    text = get!(port, "/assets", :assets)
    assert text =~ ~s(<MTConnectAssets xmlns="urn:mtconnect.org:MTConnectAssets:2.5")
    assert text =~ ~s(assetCount="0")
    assert text =~ "<Assets></Assets>"
    get!(port, "/#{ws}/assets", :assets)
    get!(port, "/assets?type=CuttingTool&count=10", :assets)
    error!(port, "/NOPE/assets", "NO_DEVICE", 404)
    error!(port, "/assets?removed=maybe", "INVALID_REQUEST")
  end

  test "JSON (MTConnect JSON v2) on Accept: application/json or format=json", %{
    port: port,
    id: id
  } do
    {200, "application/json", body} =
      MTCClient.get(port, "/probe", [{"accept", "application/json"}])

    %{"MTConnectDevices" => doc} = JSONDecode.decode(body)
    assert doc["jsonVersion"] == 2
    assert doc["Header"]["bufferSize"] == 64
    [device] = doc["Devices"]["Device"]
    assert device["name"] =~ "test"
    assert [%{"name" => "vise"}] = device["Components"]["Chuck"]

    {200, "application/json", body} = MTCClient.get(port, "/current?format=json")
    %{"MTConnectStreams" => doc} = JSONDecode.decode(body)
    streams = doc["Streams"]["DeviceStream"]
    vise = for d <- streams, c <- d["ComponentStream"], c["componentId"] == "#{id}_vise", do: c
    assert [%{"Events" => %{"ChuckState" => [%{"value" => "UNAVAILABLE"}]}}] = vise
    assert [%{"Condition" => %{"Unavailable" => [_]}}] = vise

    {400, "application/json", body} = MTCClient.get(port, "/sample?from=0&format=json")

    %{"MTConnectError" => %{"Errors" => %{"Error" => [%{"errorCode" => "OUT_OF_RANGE"}]}}} =
      JSONDecode.decode(body)

    {200, "application/json", body} =
      MTCClient.get(port, "/assets", [{"accept", "application/json"}])

    assert %{"MTConnectAssets" => %{"Header" => %{"assetCount" => 0}}} = JSONDecode.decode(body)
    error!(port, "/probe?format=yaml", "INVALID_REQUEST")
  end

  test "unknown paths and parameters are MTConnectError documents, never data", %{port: port} do
    error!(port, "/nothing/here/at/all", "INVALID_URI", 404)
    error!(port, "/currant", "INVALID_URI", 404)
    error!(port, "/current?frm=3", "INVALID_REQUEST")
    error!(port, "/probe?path=//Device", "INVALID_REQUEST")
    error!(port, "/sample?from=%zz", "INVALID_REQUEST")
  end
end
