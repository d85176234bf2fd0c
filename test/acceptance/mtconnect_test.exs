defmodule Vws.Acceptance.MTConnectTest do
  # The MTConnect agent as a client sees it: black-box requests against a real `mix vws.serve`
  # OS process (its simulated floor at time scale ×20) over real TCP — filters, at=, paging,
  # streaming, assets, JSON and the error documents — every XML document validated against the
  # 2.5 schemas (the Assets document against the standard's structure, see docs/mtconnect.md).
  use ExUnit.Case, async: true

  alias Vws.Test.{Acceptance, JSONDecode, MTCClient, XMLLint}

  @moduletag :acceptance
  @moduletag :mtconnect_schemas
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp get!(http, path, kind, status \\ 200) do
    {^status, "application/xml", body} = MTCClient.get(http, path)
    XMLLint.validate!(body, kind)
  end

  defp ids(text), do: text |> MTCClient.observations() |> Enum.map(&elem(&1, 1)) |> Enum.uniq()

  test "mix vws.serve's agent: filters, at=, paging, streaming, assets, JSON and errors" do
    # port 0: the OS picks free ports, read back from what it prints (a port picked free here
    # could be taken by one of its simulators before the dashboard binds it)
    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "0", "--http-port", "0", "--time-scale", "20"],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)

    [_, wc] =
      Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:(\d+)/, 90_000)

    [_, http] =
      Acceptance.await(proc, ~r/Dashboard and MTConnect agent: http:\/\/127\.0\.0\.1:(\d+)\//)

    {wc, http} = {String.to_integer(wc), String.to_integer(http)}

    probe = get!(http, "/probe", :devices)
    assert probe =~ ~s(<Device id="ws_VWS" name="VWS")
    assert probe =~ ~s(<Adapter id="ws_VWS_val_link" name="val_link">)

    # a stream from now on, before anything happens
    now = get!(http, "/current", :streams)
    start = MTCClient.header(now, "nextSequence")

    path =
      URI.encode_www_form(
        ~s(//Chuck[@name="vise"]//DataItem[@type="CHUCK_STATE" or @name="command"])
      )

    {sref, spid, head} = MTCClient.stream(http, "/sample?interval=0&heartbeat=500&from=#{start}")

    assert head.status == 200
    assert head.headers["content-type"] =~ "multipart/x-mixed-replace;boundary="

    # the WC opens the vise: the change is recorded, the filtered current shows it
    assert Acceptance.wc_request(wc, "*0001*F0001OPEN*") =~ ~r/^05A0001\d{3}$/
    deadline = System.monotonic_time(:millisecond) + 30_000

    assert Acceptance.await_command(wc, "FIXTURE_CMD", 2, 1, deadline) =~
             ~r/^\d\dS\d{4}0001DONE\d{3}$/

    text = get!(http, "/current?path=" <> path, :streams)
    assert Enum.sort(ids(text)) == ["ws_VWS_vise_cmd", "ws_VWS_vise_state"]
    assert text =~ ~r{<ChuckState dataItemId="ws_VWS_vise_state"[^>]*>OPEN</ChuckState>}
    assert text =~ ~r{<Message dataItemId="ws_VWS_vise_cmd"[^>]*>0001 OPEN DONE</Message>}

    # the stream carried the command, with no gap from `start`
    parts = collect_parts(sref, "0001 OPEN DONE", [])
    seqs = for p <- parts, {_, _, s, _} <- MTCClient.observations(p), do: s
    assert Enum.sort(seqs) == Enum.to_list(start..Enum.max(seqs))
    MTCClient.stop(spid)

    # paging from `start` covers the same observations exactly once
    last = MTCClient.header(get!(http, "/current", :streams), "lastSequence")

    paged =
      Stream.unfold(start, fn
        from when from > last ->
          nil

        from ->
          {200, _, page} = MTCClient.get(http, "/sample?from=#{from}&count=20")
          {MTCClient.observations(page), MTCClient.header(page, "nextSequence")}
      end)
      |> Enum.concat()
      |> Enum.map(&elem(&1, 2))

    # (a document groups its observations by component: sorted here)
    paged = Enum.sort(paged)
    assert paged == Enum.to_list(start..List.last(paged))
    assert List.last(paged) >= last

    # at=: the state before the command
    before = get!(http, "/current?at=#{start - 1}&path=" <> path, :streams)
    assert before =~ ~r{<Message dataItemId="ws_VWS_vise_cmd"[^>]*>NO COMMAND YET</Message>}

    # assets, JSON
    assets = get!(http, "/assets", :assets)
    assert assets =~ ~s(assetCount="0")

    {200, "application/json", json} =
      MTCClient.get(http, "/current?path=" <> path, [{"accept", "application/json"}])

    assert %{"MTConnectStreams" => %{"jsonVersion" => 2, "Streams" => %{"DeviceStream" => [_]}}} =
             JSONDecode.decode(json)

    # what the agent cannot serve
    assert get!(http, "/sample?from=0", :error, 400) =~ ~s(errorCode="OUT_OF_RANGE")
    assert get!(http, "/current?at=#{last + 100}", :error, 400) =~ ~s(errorCode="OUT_OF_RANGE")

    assert get!(http, "/current?path=" <> URI.encode_www_form("//Nothing"), :error, 400) =~
             ~s(errorCode="INVALID_PATH")

    assert get!(http, "/sample?count=many", :error, 400) =~ ~s(errorCode="INVALID_REQUEST")
    assert get!(http, "/current?bogus=1", :error, 400) =~ ~s(errorCode="INVALID_REQUEST")
    assert get!(http, "/VWS/probee", :error, 404) =~ ~s(errorCode="INVALID_URI")
    assert get!(http, "/NOPE/current", :error, 404) =~ ~s(errorCode="NO_DEVICE")
    assert get!(http, "/assets?removed=perhaps", :error, 400) =~ ~s(errorCode="INVALID_REQUEST")

    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 30_000) == 0, Acceptance.output(proc)
  end

  defp collect_parts(ref, until, acc) do
    receive do
      {:mtc_part, ^ref, doc} ->
        # (validated once, below: xmllint costs about half a second a document)
        if doc =~ until do
          XMLLint.validate!(doc, :streams)
          Enum.reverse([doc | acc])
        else
          collect_parts(ref, until, [doc | acc])
        end
    after
      30_000 -> flunk("the stream never carried #{until}")
    end
  end
end
