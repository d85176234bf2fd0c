defmodule Vws.Ops.MTConnect.XML do
  @moduledoc """
  MTConnect 2.5 response documents as iodata: `MTConnectDevices` (probe), `MTConnectStreams`
  (current, sample) and `MTConnectError`. Pure: no processes, no I/O. Every text and attribute
  value is escaped (`escape/1`), so a status text with `<`, `&` or quotes cannot break a document.

      iex> Vws.Ops.MTConnect.XML.escape(~s(TRAY "1" <A&B>))
      "TRAY &quot;1&quot; &lt;A&amp;B&gt;"
  """

  alias Vws.Ops.MTConnect.Model

  @version "2.5.0.0"
  @ns "urn:mtconnect.org:"
  @schemas "http://schemas.mtconnect.org/schemas/"

  @typedoc """
  The header's facts: `creation_time`, `sender`, `instance_id`, `buffer_size`, and for devices and
  streams `model_change_time`; for streams `first_sequence`, `last_sequence`, `next_sequence`.
  """
  @type header :: map

  @typedoc "One observation: the data item, its value, sequence number and timestamp."
  @type observation :: %{
          item: Model.item(),
          value: String.t(),
          sequence: pos_integer,
          timestamp: String.t()
        }

  @doc "The MTConnect version these documents declare."
  @spec version() :: String.t()
  def version, do: @version

  @doc "An `MTConnectDevices` document (the answer to `/probe`)."
  @spec devices(header, [Model.device()]) :: iodata
  def devices(header, devices) do
    document("MTConnectDevices", [
      header_tag(header, [
        {"deviceModelChangeTime", header.model_change_time},
        {"bufferSize", header.buffer_size},
        {"assetBufferSize", Map.get(header, :asset_buffer_size, 1024)},
        {"assetCount", 0}
      ]),
      element("Devices", [], Enum.map(devices, &device/1))
    ])
  end

  defp device(d) do
    kind = Map.get(d, :kind, "Device")

    description =
      if kind == "Agent",
        do: element("Description", [{"manufacturer", "VWS"}], ["MTConnect agent of the VWS CEC"]),
        else:
          element(
            "Description",
            [{"manufacturer", "NBS AMRF"}, {"model", "Vertical Workstation"}],
            [
              escape("Vertical Workstation #{d.name}: VMC, robot, gripper, vise, trays, pallet")
            ]
          )

    element(kind, [{"id", d.id}, {"name", d.name}, {"uuid", d.uuid}], [
      description,
      data_items(d.items),
      components(d.components)
    ])
  end

  defp component(c) do
    element(c.type, [{"id", c.id}, {"name", c.name}], [
      data_items(c.items),
      components(c.components)
    ])
  end

  defp components([]), do: []
  defp components(list), do: element("Components", [], Enum.map(list, &component/1))

  defp data_items([]), do: []

  defp data_items(items) do
    element(
      "DataItems",
      [],
      for i <- items do
        attrs =
          [{"id", i.id}, {"type", i.type}, {"category", category(i.category)}] ++
            optional("name", Map.get(i, :name)) ++
            optional("subType", Map.get(i, :sub_type)) ++
            optional("units", i.units) ++
            if(i.type in ["PATH_POSITION", "POSITION"],
              do: [{"coordinateSystem", "MACHINE"}],
              else: []
            )

        case Map.get(i, :deadband) do
          nil ->
            tag("DataItem", attrs)

          band ->
            element("DataItem", attrs, [
              element("Filters", [], [
                element("Filter", [{"type", "MINIMUM_DELTA"}], [number_text(band)])
              ])
            ])
        end
      end
    )
  end

  defp category(:event), do: "EVENT"
  defp category(:sample), do: "SAMPLE"
  defp category(:condition), do: "CONDITION"

  defp optional(_name, nil), do: []
  defp optional(name, value), do: [{name, value}]

  @doc """
  A value as MTConnect writes it: text as it is; a number with at most three decimals (a whole
  number without any); a condition by its text.

      iex> Vws.Ops.MTConnect.XML.value_text(50.04)
      "50.04"
      iex> Vws.Ops.MTConnect.XML.value_text(4990.0)
      "4990"
  """
  @spec value_text(term) :: String.t()
  def value_text(v) when is_binary(v), do: v
  def value_text(v) when is_integer(v), do: Integer.to_string(v)
  def value_text(v) when is_float(v), do: number_text(v)
  def value_text({:condition, _level, _code, text}), do: text

  defp number_text(v) when is_integer(v), do: Integer.to_string(v)

  defp number_text(v) when is_float(v) do
    r = Float.round(v, 3)

    if r == Float.round(r),
      do: Integer.to_string(trunc(r)),
      else: :erlang.float_to_binary(r, [:short])
  end

  @doc """
  An `MTConnectStreams` document (the answer to `/current` and `/sample`): the observations
  grouped by device, then by component, in sequence order within each group.
  """
  @spec streams(header, [observation]) :: iodata
  def streams(header, observations) do
    document("MTConnectStreams", [
      header_tag(header, [
        {"deviceModelChangeTime", header.model_change_time},
        {"bufferSize", header.buffer_size},
        {"nextSequence", header.next_sequence},
        {"firstSequence", header.first_sequence},
        {"lastSequence", header.last_sequence}
      ]),
      element(
        "Streams",
        [],
        for {{name, uuid}, components} <- stream_groups(observations) do
          element("DeviceStream", [{"name", name}, {"uuid", uuid}], component_streams(components))
        end
      )
    ])
  end

  defp component_streams(components) do
    for {{type, id, name}, by} <- components do
      element("ComponentStream", [{"component", type}, {"componentId", id}, {"name", name}], [
        observations("Samples", by.sample),
        observations("Events", by.event),
        observations("Condition", by.condition)
      ])
    end
  end

  @doc """
  The observations of a streams document as both formats nest them (`Vws.Ops.MTConnect.JSON`
  too): by device (`{name, uuid}`), then by component (`{type, id, name}`), each in the order it
  first appears, then by category (`%{sample, event, condition}`).
  """
  @spec stream_groups([observation]) :: [
          {{String.t(), String.t()},
           [{{String.t(), String.t(), String.t()}, %{atom => [observation]}}]}
        ]
  def stream_groups(observations) do
    for {device, obs} <- group(observations, &{&1.item.device, &1.item.device_uuid}) do
      components =
        for {component, cobs} <-
              group(obs, &{&1.item.component, &1.item.component_id, &1.item.component_name}) do
          by = Enum.group_by(cobs, & &1.item.category)
          {component, Map.new([:sample, :event, :condition], &{&1, Map.get(by, &1, [])})}
        end

      {device, components}
    end
  end

  defp observations(_, []), do: []

  defp observations(wrapper, obs) do
    element(
      wrapper,
      [],
      for o <- Enum.sort_by(obs, & &1.sequence) do
        attrs =
          [
            {"dataItemId", o.item.id},
            {"timestamp", o.timestamp},
            {"sequence", o.sequence}
          ] ++ optional("name", Map.get(o.item, :name)) ++ optional("subType", o.item[:sub_type])

        case o.value do
          {:condition, level, code, text} ->
            # an active condition names its activation (2.5: conditionId): its native code
            attrs =
              attrs ++
                [{"type", o.item.type}] ++
                optional("nativeCode", code) ++
                if(level in ["Fault", "Warning"],
                  do: [{"conditionId", code || o.item.id}],
                  else: []
                )

            if text == "", do: tag(level, attrs), else: element(level, attrs, [escape(text)])

          value ->
            element(o.item.element, attrs, [escape(value_text(value))])
        end
      end
    )
  end

  # Groups keeping the order in which each key first appears.
  defp group(list, key_fun) do
    {keys, groups} =
      Enum.reduce(list, {[], %{}}, fn x, {keys, groups} ->
        k = key_fun.(x)
        keys = if Map.has_key?(groups, k), do: keys, else: [k | keys]
        {keys, Map.update(groups, k, [x], &[x | &1])}
      end)

    for k <- Enum.reverse(keys), do: {k, Enum.reverse(Map.fetch!(groups, k))}
  end

  @doc """
  An `MTConnectError` document with one error: `code` is one of the standard's error codes
  (`"OUT_OF_RANGE"`, `"NO_DEVICE"`, `"INVALID_REQUEST"`, `"INVALID_URI"`, …).
  """
  @spec error(header, String.t(), String.t()) :: iodata
  def error(header, code, text) do
    document("MTConnectError", [
      header_tag(header, [
        {"bufferSize", header.buffer_size}
      ]),
      element("Errors", [], [element("Error", [{"errorCode", code}], [escape(text)])])
    ])
  end

  @doc """
  An `MTConnectAssets` document (the answer to `/assets`): the header the standard asks for
  (`instanceId`, `version`, `sender`, `creationTime`, `assetBufferSize`, `assetCount`) and the
  assets, none on this agent (the 2.5 Assets schema is not among the shipped schemas: its shape
  is checked by the tests against the standard's text, see `docs/mtconnect.md`).
  """
  @spec assets(header, [iodata]) :: iodata
  def assets(header, assets) do
    document("MTConnectAssets", [
      header_tag(header, [
        {"deviceModelChangeTime", header.model_change_time},
        {"assetBufferSize", header.asset_buffer_size},
        {"assetCount", length(assets)}
      ]),
      element("Assets", [], assets)
    ])
  end

  @doc "An ISO 8601 UTC timestamp with microseconds, as MTConnect writes them."
  @spec timestamp(integer) :: String.t()
  def timestamp(system_us) do
    system_us
    |> DateTime.from_unix!(:microsecond)
    |> DateTime.to_iso8601()
  end

  ## XML

  defp document(root, body) do
    schema = root <> "_2.5.xsd"
    ns = @ns <> root <> ":2.5"

    [
      ~s(<?xml version="1.0" encoding="UTF-8"?>\n),
      element(
        root,
        [
          {"xmlns", ns},
          {"xmlns:xsi", "http://www.w3.org/2001/XMLSchema-instance"},
          {"xsi:schemaLocation", "#{ns} #{@schemas}#{schema}"}
        ],
        body
      ),
      ?\n
    ]
  end

  defp element(name, attrs, children),
    do: ["<", name, attributes(attrs), ">", children, "</", name, ">"]

  defp tag(name, attrs), do: ["<", name, attributes(attrs), "/>"]

  defp attributes(attrs) do
    for {k, v} <- attrs, do: [" ", k, "=\"", escape(to_text(v)), "\""]
  end

  defp to_text(v) when is_binary(v), do: v
  defp to_text(v) when is_integer(v), do: Integer.to_string(v)
  defp to_text(v) when is_atom(v), do: Atom.to_string(v)

  @doc """
  Escapes text for XML content and attribute values. Characters XML 1.0 cannot carry at all
  (control characters other than tab, LF and CR, and bytes that are not UTF-8) become `?`.
  """
  @spec escape(String.t()) :: String.t()
  def escape(text) do
    # (most values are plain: numbers, words — returned as they are, without a copy)
    if plain?(text), do: text, else: text |> valid_chars() |> do_escape()
  end

  # printable ASCII with nothing to escape
  defp plain?(<<c, rest::binary>>)
       when c >= 0x20 and c <= 0x7E and c != ?& and c != ?< and c != ?> and c != ?" and c != ?',
       do: plain?(rest)

  defp plain?(<<>>), do: true
  defp plain?(_), do: false

  defp do_escape(text) do
    text
    |> String.replace("&", "&amp;")
    |> String.replace("<", "&lt;")
    |> String.replace(">", "&gt;")
    |> String.replace("\"", "&quot;")
    |> String.replace("'", "&apos;")
  end

  defp valid_chars(text), do: valid_chars(text, [])

  defp valid_chars(<<>>, acc), do: acc |> Enum.reverse() |> IO.iodata_to_binary()

  defp valid_chars(<<c::utf8, rest::binary>>, acc)
       when c in [0x9, 0xA, 0xD] or (c >= 0x20 and c <= 0xD7FF) or (c >= 0xE000 and c <= 0xFFFD) or
              c >= 0x10000,
       do: valid_chars(rest, [<<c::utf8>> | acc])

  defp valid_chars(<<_::utf8, rest::binary>>, acc), do: valid_chars(rest, [?? | acc])
  defp valid_chars(<<_, rest::binary>>, acc), do: valid_chars(rest, [?? | acc])

  # Every document's Header: who and when, then the attributes of its kind.
  defp header_tag(header, attributes) do
    tag(
      "Header",
      [
        {"creationTime", header.creation_time},
        {"sender", header.sender},
        {"instanceId", header.instance_id},
        {"version", @version}
      ] ++ attributes
    )
  end
end
