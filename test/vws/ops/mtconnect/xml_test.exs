defmodule Vws.Ops.MTConnect.XMLTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Ops.MTConnect.{Model, XML}
  alias Vws.Test.XMLLint

  doctest Vws.Ops.MTConnect.XML

  @header %{
    creation_time: "2024-05-01T12:00:00.000000Z",
    model_change_time: "2024-05-01T11:00:00.000000Z",
    sender: "vws-test",
    instance_id: 1_714_560_000,
    buffer_size: 16,
    first_sequence: 1,
    last_sequence: 3,
    next_sequence: 4
  }

  test "escape/1: markup characters, and characters XML cannot carry" do
    assert XML.escape("a<b>&\"'") == "a&lt;b&gt;&amp;&quot;&apos;"
    assert XML.escape(<<"A", 0, 0x1B, "B", 0xFF>>) == "A??B?"
    assert XML.escape("tab\there é→") == "tab\there é→"
  end

  defp escape_rule(<<>>, acc), do: acc

  defp escape_rule(<<c::utf8, rest::binary>>, acc) do
    out =
      cond do
        c == ?& ->
          "&amp;"

        c == ?< ->
          "&lt;"

        c == ?> ->
          "&gt;"

        c == ?" ->
          "&quot;"

        c == ?' ->
          "&apos;"

        c in [0x9, 0xA, 0xD] or (c >= 0x20 and c <= 0xD7FF) or (c >= 0xE000 and c <= 0xFFFD) or
            c >= 0x10000 ->
          <<c::utf8>>

        true ->
          "?"
      end

    escape_rule(rest, acc <> out)
  end

  defp escape_rule(<<_, rest::binary>>, acc), do: escape_rule(rest, acc <> "?")

  test "property: escape/1's plain text fast way gives what the character by character way gives" do
    # the rule written out: characters XML cannot carry become ?, markup becomes entities
    slow = &escape_rule(&1, "")

    text =
      :proper_types.oneof([
        :proper_types.binary(),
        :proper_unicode.utf8(),
        :proper_types.list(:proper_types.elements(~c"AZ09 .-_&<>\"'\t")),
        :proper_types.list(:proper_types.integer(0, 0x7F))
      ])

    property =
      :proper.forall(text, fn t ->
        t = if is_list(t), do: List.to_string(t), else: t
        XML.escape(t) == slow.(t)
      end)

    assert_property(property, 1_000)
  end

  @tag :mtconnect_schemas
  test "a probe of two workstations validates (ids that need cleaning too)" do
    XML.devices(@header, [Model.device("VWS"), Model.device("cell <2> & co")])
    |> XMLLint.validate!(:devices)
  end

  @tag :mtconnect_schemas
  test "streams with hostile text values validate and keep the text" do
    d = Model.device("VWS")
    items = Map.new(Model.items(d), &{&1.id, &1})

    obs = [
      %{item: items["ws_VWS_vise_msg"], value: ~s(VISE <"LOCKED"> & 'more'), sequence: 1},
      %{item: items["ws_VWS_robot_path_pos"], value: "1.5 -2 300", sequence: 2},
      %{item: items["ws_VWS_avail"], value: "AVAILABLE", sequence: 3}
    ]

    obs = Enum.map(obs, &Map.put(&1, :timestamp, "2024-05-01T12:00:00.000001Z"))
    text = XML.streams(@header, obs) |> XMLLint.validate!(:streams)
    assert text =~ "VISE &lt;&quot;LOCKED&quot;&gt; &amp; &apos;more&apos;"

    assert text =~
             ~r{<Samples><PathPosition dataItemId="ws_VWS_robot_path_pos"[^>]*>1.5 -2 300</PathPosition></Samples>}
  end

  @tag :mtconnect_schemas
  test "an empty stream validates" do
    XML.streams(@header, []) |> XMLLint.validate!(:streams)
  end

  @tag :mtconnect_schemas
  test "error documents validate" do
    for code <- ~w(OUT_OF_RANGE NO_DEVICE INVALID_REQUEST) do
      XML.error(@header, code, "'from' must be <= 4 & > 0") |> XMLLint.validate!(:error)
    end
  end
end
