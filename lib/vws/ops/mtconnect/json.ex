defmodule Vws.Ops.MTConnect.JSON do
  @moduledoc """
  The MTConnect documents in the MTConnect JSON format, version 2 — the one the reference agent
  (cppagent 2.x) writes by default (`JsonVersion = 2`): the root object named as the XML root
  (`MTConnectDevices`, `MTConnectStreams`, `MTConnectAssets`, `MTConnectError`) holding
  `jsonVersion`, `schemaVersion`, the `Header` (its attributes as members) and the body, where
  repeated elements of one name become an array under that name (`"DataItems": {"DataItem":
  [...]}`, `"Events": {"Execution": [...]}`) and an element's text is its `value`. Answered for
  `Accept: application/json` (or `format=json`). Pure.

      iex> doc = Vws.Ops.MTConnect.JSON.error(%{creation_time: "t", sender: "s", instance_id: 1, buffer_size: 8}, "OUT_OF_RANGE", "'from' …")
      iex> IO.iodata_to_binary(doc) =~ ~s("Errors":{"Error":[{"errorCode":"OUT_OF_RANGE")
      true
  """

  alias Vws.Ops.MTConnect.{Model, XML}

  @json_version 2

  @doc "The probe document as JSON."
  @spec devices(map, [Model.device()]) :: iodata
  def devices(header, devices) do
    {agents, others} = Enum.split_with(devices, &(Map.get(&1, :kind) == "Agent"))

    body =
      %{}
      |> put_list("Agent", Enum.map(agents, &device/1))
      |> put_list("Device", Enum.map(others, &device/1))

    root("MTConnectDevices", %{
      "Header" =>
        Map.merge(base_header(header), %{
          "deviceModelChangeTime" => header.model_change_time,
          "bufferSize" => header.buffer_size,
          "assetBufferSize" => Map.get(header, :asset_buffer_size, 1024),
          "assetCount" => 0
        }),
      "Devices" => body
    })
  end

  defp device(d) do
    %{"id" => d.id, "name" => d.name, "uuid" => d.uuid}
    |> Map.merge(contents(d))
  end

  defp contents(c) do
    m = %{}

    m =
      if c.items == [],
        do: m,
        else: Map.put(m, "DataItems", %{"DataItem" => Enum.map(c.items, &data_item/1)})

    if c.components == [] do
      m
    else
      comps =
        Enum.group_by(c.components, & &1.type, fn child ->
          Map.merge(%{"id" => child.id, "name" => child.name}, contents(child))
        end)

      Map.put(m, "Components", comps)
    end
  end

  defp data_item(i) do
    %{"id" => i.id, "type" => i.type, "category" => String.upcase(to_string(i.category))}
    |> put("name", i[:name])
    |> put("subType", i[:sub_type])
    |> put("units", i[:units])
    |> then(fn m ->
      if i[:deadband],
        do:
          Map.put(m, "Filters", %{
            "Filter" => [%{"type" => "MINIMUM_DELTA", "value" => i.deadband}]
          }),
        else: m
    end)
  end

  @doc "A streams document (current, sample) as JSON."
  @spec streams(map, [XML.observation()]) :: iodata
  def streams(header, observations) do
    device_streams =
      for {{name, uuid}, components} <- XML.stream_groups(observations) do
        %{
          "name" => name,
          "uuid" => uuid,
          "ComponentStream" =>
            for {{type, id, cname}, by} <- components do
              %{"component" => type, "componentId" => id, "name" => cname}
              |> put_group("Samples", by.sample)
              |> put_group("Events", by.event)
              |> put_group("Condition", by.condition)
            end
        }
      end

    root("MTConnectStreams", %{
      "Header" =>
        Map.merge(base_header(header), %{
          "deviceModelChangeTime" => header.model_change_time,
          "bufferSize" => header.buffer_size,
          "nextSequence" => header.next_sequence,
          "firstSequence" => header.first_sequence,
          "lastSequence" => header.last_sequence
        }),
      "Streams" => if(device_streams == [], do: %{}, else: %{"DeviceStream" => device_streams})
    })
  end

  defp put_group(m, _key, []), do: m

  defp put_group(m, key, obs) do
    entries =
      obs
      |> Enum.sort_by(& &1.sequence)
      |> Enum.group_by(&element_name/1, &observation/1)

    Map.put(m, key, entries)
  end

  defp element_name(%{value: {:condition, level, _, _}}), do: level
  defp element_name(o), do: o.item.element

  defp observation(o) do
    base =
      %{"dataItemId" => o.item.id, "timestamp" => o.timestamp, "sequence" => o.sequence}
      |> put("name", o.item[:name])
      |> put("subType", o.item[:sub_type])

    case o.value do
      {:condition, _level, code, text} ->
        base
        |> Map.put("type", o.item.type)
        |> put("nativeCode", code)
        |> then(&if code, do: Map.put(&1, "conditionId", code), else: &1)
        |> then(&if text == "", do: &1, else: Map.put(&1, "value", text))

      v when is_number(v) ->
        Map.put(base, "value", v)

      v ->
        Map.put(base, "value", XML.value_text(v))
    end
  end

  @doc "An assets document as JSON (no assets here)."
  @spec assets(map, list) :: iodata
  def assets(header, assets) do
    root("MTConnectAssets", %{
      "Header" =>
        Map.merge(base_header(header), %{
          "assetBufferSize" => header.asset_buffer_size,
          "assetCount" => length(assets)
        }),
      "Assets" => %{}
    })
  end

  @doc "An error document as JSON."
  @spec error(map, String.t(), String.t()) :: iodata
  def error(header, code, text) do
    root("MTConnectError", %{
      "Header" => Map.put(base_header(header), "bufferSize", header.buffer_size),
      "Errors" => %{"Error" => [%{"errorCode" => code, "value" => text}]}
    })
  end

  defp base_header(h) do
    %{
      "creationTime" => h.creation_time,
      "sender" => h.sender,
      "instanceId" => h.instance_id,
      "version" => XML.version()
    }
  end

  defp root(name, body) do
    Vws.Ops.Web.JSON.encode(%{
      name => Map.merge(body, %{"jsonVersion" => @json_version, "schemaVersion" => "2.5"})
    })
  end

  defp put(m, _k, nil), do: m
  defp put(m, k, v), do: Map.put(m, k, v)

  defp put_list(m, _k, []), do: m
  defp put_list(m, k, list), do: Map.put(m, k, list)
end
