defmodule Vws.Codecs.SCPITest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.SCPI
  alias Vws.Codecs.SCPI.Error

  doctest Vws.Codecs.SCPI
  doctest Vws.Codecs.SCPI.Error

  defp line(iodata), do: IO.iodata_to_binary(iodata)

  # Golden vectors: lines from PROTOCOLS.md §4; numbers and channel-list folding computed
  # independently with python3 ('%+.8E' % v, and a separate folding routine).
  describe "golden commands" do
    @golden [
      {:idn?, "*IDN?\n"},
      {:rst, "*RST\n"},
      {:cls, "*CLS\n"},
      {:syst_err?, "SYST:ERR?\n"},
      {{:meas_volt_dc?, Enum.to_list(101..116)}, "MEAS:VOLT:DC? (@101:116)\n"},
      {{:meas_res?, [117]}, "MEAS:RES? (@117)\n"},
      {{:meas_volt_dc?, [101, 105, 110]}, "MEAS:VOLT:DC? (@101,105,110)\n"},
      {{:rout_clos, [201]}, "ROUT:CLOS (@201)\n"},
      {{:rout_open, [201]}, "ROUT:OPEN (@201)\n"},
      {{:rout_clos?, [201]}, "ROUT:CLOS? (@201)\n"},
      {{:rout_clos?, [101, 102, 201, 202, 203, 119, 120, 201]},
       "ROUT:CLOS? (@101,102,201:203,119,120,201)\n"},
      {:clamp_pallet, "CLAMP_PALLET\n"},
      {:release_pallet, "RELEASE_PALLET\n"},
      {:status?, "STATUS?\n"},
      {:pallet?, "PALLET?\n"}
    ]

    test "encode to the spec's lines and decode back" do
      for {term, text} <- @golden do
        assert line(SCPI.encode_command(term)) == text
        assert SCPI.decode_command(text) == {:ok, term}
      end
    end

    test "long forms, lower case, leading colon, blanks and CR LF are the same commands" do
      for {text, term} <- [
            {"MEASure:VOLTage:DC? (@101:116)\r\n", {:meas_volt_dc?, Enum.to_list(101..116)}},
            {"meas:res? (@117)", {:meas_res?, [117]}},
            {":ROUTe:CLOSe (@201,202)", {:rout_clos, [201, 202]}},
            {"route:close? (@210)", {:rout_clos?, [210]}},
            {"  ROUT:OPEN\t (@205:206) \t", {:rout_open, [205, 206]}},
            {"SYSTem:ERRor?", :syst_err?},
            {"SYST:ERR:NEXT?", :syst_err?},
            {"*idn?", :idn?},
            {"pallet?\r\n", :pallet?}
          ] do
        assert SCPI.decode_command(text) == {:ok, term}, text
      end
    end

    test "every error reason" do
      for {text, reason} <- [
            {"", :empty},
            {" \t ", :empty},
            {"*RST\x00", :bad_character},
            {"*RST\n\n", :bad_character},
            {"MEAS:VOLT:DCX? (@101)", :undefined_header},
            {"MEASU:RES? (@117)", :undefined_header},
            {"::ROUT:OPEN (@201)", :undefined_header},
            {"ROUT:CLOS", :missing_parameter},
            {"*IDN? 1", :unexpected_parameter},
            {"ROUT:CLOS @201", :bad_channel_list},
            {"ROUT:CLOS (@201", :bad_channel_list},
            {"ROUT:CLOS (@)", :bad_channel_list},
            {"ROUT:CLOS (@201,)", :bad_channel_list},
            {"ROUT:CLOS (@ 201)", :bad_channel_list},
            {"ROUT:CLOS (@2011)", :bad_channel_list},
            {"ROUT:CLOS (@200)", :channel_out_of_range},
            {"ROUT:CLOS (@099)", :channel_out_of_range},
            {"ROUT:CLOS (@205:201)", :channel_out_of_range},
            {"ROUT:CLOS (@119:201)", :channel_out_of_range}
          ] do
        assert {:error, %Error{reason: ^reason} = error} = SCPI.decode_command(text), text
        assert is_binary(Exception.message(error))
      end
    end

    test "encoding a non-command raises" do
      assert_raise ArgumentError, fn -> SCPI.encode_command({:rout_clos, []}) end
      assert_raise ArgumentError, fn -> SCPI.encode_command({:rout_clos, [200]}) end
      assert_raise ArgumentError, fn -> SCPI.encode_command(:reboot) end
    end
  end

  describe "golden responses" do
    test "readings in +d.dddddddddE+dd form" do
      values = [1.23456789, -0.5, 9.9e37, 0.0, 370.012, 5.0, 2.5e-3, -1.0e-300, 1_234_567.891]

      expected =
        "+1.23456789E+00,-5.00000000E-01,+9.90000000E+37,+0.00000000E+00,+3.70012000E+02," <>
          "+5.00000000E+00,+2.50000000E-03,-1.00000000E-300,+1.23456789E+06\n"

      assert line(SCPI.encode_response(values)) == expected
      query = {:meas_volt_dc?, Enum.to_list(101..109)}
      assert {:ok, decoded} = SCPI.decode_response(query, expected)

      assert decoded == [
               1.23456789,
               -0.5,
               9.9e37,
               0.0,
               370.012,
               5.0,
               2.5e-3,
               -1.0e-300,
               1.23456789e6
             ]
    end

    test "any SCPI number form is read" do
      query = {:meas_res?, [101, 102, 103, 104, 105, 106]}

      assert SCPI.decode_response(query, "1,-2,+.5,3.,4E2,-1.5e-3\r\n") ==
               {:ok, [1.0, -2.0, 0.5, 3.0, 400.0, -0.0015]}
    end

    test "states, error queue, identity, hydraulic status and pallet" do
      assert line(SCPI.encode_response([true, false, true])) == "1,0,1\n"

      assert SCPI.decode_response({:rout_clos?, [201, 202, 203]}, "1,0,1\n") ==
               {:ok, [true, false, true]}

      assert line(SCPI.encode_response({0, "No error"})) == ~s(+0,"No error"\n)
      assert SCPI.decode_response(:syst_err?, ~s(+0,"No error")) == {:ok, {0, "No error"}}

      assert line(SCPI.encode_response({-113, ~s(Undefined "header")})) ==
               ~s(-113,"Undefined ""header"""\n)

      assert SCPI.decode_response(:syst_err?, ~s(-113,"Undefined ""header""")) ==
               {:ok, {-113, ~s(Undefined "header")}}

      idn = %{manufacturer: "HEWLETT-PACKARD", model: "34970A", serial: "0", firmware: "13-2-2"}
      assert line(SCPI.encode_response(idn)) == "HEWLETT-PACKARD,34970A,0,13-2-2\n"
      assert SCPI.decode_response(:idn?, "HEWLETT-PACKARD,34970A,0,13-2-2\n") == {:ok, idn}

      assert line(SCPI.encode_response(:done)) == "DONE\n"
      assert line(SCPI.encode_response(:executing)) == "EXECUTING\n"
      assert line(SCPI.encode_response({:error, "NO PRESSURE"})) == "ERROR NO PRESSURE\n"
      assert SCPI.decode_response(:status?, "EXECUTING") == {:ok, :executing}
      assert SCPI.decode_response(:status?, "ERROR NO PRESSURE") == {:ok, {:error, "NO PRESSURE"}}

      pallet = %{clamped: false, x: true, y: false, force1_n: 0.0, force2_n: 1200.0}

      assert line(SCPI.encode_response(pallet)) ==
               "PALLET NOT CLAMPED X=1 Y=0 F1=+0.00000000E+00 F2=+1.20000000E+03\n"

      assert SCPI.decode_response(
               :pallet?,
               "PALLET NOT CLAMPED X=1 Y=0 F1=+0.00000000E+00 F2=+1.20000000E+03"
             ) == {:ok, pallet}
    end

    test "a response that does not fit its query is refused" do
      bad = fn query, text ->
        assert {:error, %Error{reason: :bad_response}} = SCPI.decode_response(query, text), text
      end

      bad.({:meas_volt_dc?, [101, 102]}, "+1.0E+00")
      bad.({:meas_volt_dc?, [101]}, "+1.0E+00,+2.0E+00")
      bad.({:meas_volt_dc?, [101]}, "1.0.0")
      bad.({:meas_volt_dc?, [101]}, "1E99999")
      bad.({:meas_res?, [117]}, "")
      bad.({:rout_clos?, [201]}, "2")
      bad.({:rout_clos?, [201]}, "1,0")
      bad.(:syst_err?, ~s(+0,"No "error"))
      bad.(:syst_err?, "+0,No error")
      bad.(:idn?, "HP,34970A,0")
      bad.(:status?, "ERROR ")
      bad.(:status?, "done")
      bad.(:pallet?, "PALLET CLAMPED X=1 Y=1 F1=1")

      assert {:error, %Error{reason: :no_response}} = SCPI.decode_response(:rst, "1")
      assert {:error, %Error{reason: :bad_character}} = SCPI.decode_response(:idn?, "a\x01b")
    end

    test "the error queue entries" do
      assert Error.scpi_error(%Error{reason: :line_too_long}) == {-363, "Input buffer overrun"}
      assert Error.scpi_error(%Error{reason: :missing_parameter}) == {-109, "Missing parameter"}
    end
  end

  describe "line decoder" do
    test "cuts at LF, drops CR, keeps partial lines" do
      {out, d} = SCPI.feed(SCPI.new(), "*RST\r\n*IDN?\nMEAS")
      assert out == ["*RST", "*IDN?"]
      {out, d} = SCPI.feed(d, ":RES? (@117)\n")
      assert out == ["MEAS:RES? (@117)"]
      assert d.buffer == ""
    end

    test "an overlong line is reported once and skipped, the buffer stays bounded" do
      d = SCPI.new(max_line: 8)
      {out, d} = SCPI.feed(d, "0123456789")
      assert [{:error, %Error{reason: :line_too_long, max: 8}}] = out
      assert byte_size(d.buffer) <= 8
      {out, d} = SCPI.feed(d, String.duplicate("x", 100))
      assert out == []
      {out, d} = SCPI.feed(d, "yy\n*RST\n012345678\nok\n")
      assert [_, {:error, %Error{reason: :line_too_long}}, "ok"] = out
      assert hd(out) == "*RST"
      assert d.buffer == ""
    end
  end

  ## Properties

  defp channel_gen do
    :proper_types.bind(
      {:proper_types.integer(1, 9), :proper_types.integer(1, 99)},
      fn {slot, n} -> slot * 100 + n end,
      false
    )
  end

  defp channels_gen do
    :proper_types.oneof([
      :proper_types.non_empty(:proper_types.list(channel_gen())),
      # runs, so ranges get encoded too
      :proper_types.bind(
        {:proper_types.integer(1, 9), :proper_types.integer(1, 99), :proper_types.integer(0, 20)},
        fn {slot, first, len} ->
          last = min(first + len, 99)
          Enum.to_list((slot * 100 + first)..(slot * 100 + last))
        end,
        false
      )
    ])
  end

  defp command_gen do
    :proper_types.oneof([
      :proper_types.oneof([
        :idn?,
        :rst,
        :cls,
        :syst_err?,
        :clamp_pallet,
        :release_pallet,
        :status?,
        :pallet?
      ]),
      {:proper_types.oneof([:meas_volt_dc?, :meas_res?, :rout_clos, :rout_open, :rout_clos?]),
       channels_gen()}
    ])
  end

  test "property: every command round-trips" do
    assert_property(
      :proper.forall(command_gen(), fn command ->
        SCPI.decode_command(line(SCPI.encode_command(command))) == {:ok, command}
      end),
      300
    )
  end

  defp text_gen do
    :proper_types.bind(
      :proper_types.list(:proper_types.integer(0x20, 0x7E)),
      &List.to_string/1,
      false
    )
  end

  defp response_case_gen do
    float = :proper_types.oneof([:proper_types.float(), :proper_types.integer(-1000, 1000)])

    :proper_types.oneof([
      :proper_types.bind(
        :proper_types.non_empty(:proper_types.list(float)),
        fn values -> {{:meas_volt_dc?, Enum.map(values, fn _ -> 101 end)}, values} end,
        false
      ),
      :proper_types.bind(
        :proper_types.non_empty(:proper_types.list(:proper_types.boolean())),
        fn states -> {{:rout_clos?, Enum.map(states, fn _ -> 201 end)}, states} end,
        false
      ),
      :proper_types.bind(
        {:proper_types.integer(-999, 999), text_gen()},
        fn {code, text} -> {:syst_err?, {code, text}} end,
        false
      ),
      :proper_types.bind(
        :proper_types.oneof([:done, :executing, {:error, text_gen()}]),
        fn
          {:error, ""} -> {:status?, {:error, "X"}}
          status -> {:status?, status}
        end,
        false
      ),
      :proper_types.bind(
        {:proper_types.boolean(), :proper_types.boolean(), :proper_types.boolean(), float, float},
        fn {c, x, y, f1, f2} ->
          {:pallet?, %{clamped: c, x: x, y: y, force1_n: f1, force2_n: f2}}
        end,
        false
      )
    ])
  end

  defp close?(a, b) when is_number(a) and is_number(b),
    do: abs(a - b) <= 1.0e-8 * max(abs(a), abs(b)) + 1.0e-300

  defp close?(a, b) when is_list(a) and is_list(b),
    do: length(a) == length(b) and Enum.all?(Enum.zip(a, b), fn {x, y} -> close?(x, y) end)

  defp close?(%{} = a, %{} = b), do: Enum.all?(a, fn {k, v} -> close?(v, Map.fetch!(b, k)) end)
  defp close?(a, b), do: a == b

  test "property: every response round-trips (readings to nine digits) and re-encodes identically" do
    assert_property(
      :proper.forall(response_case_gen(), fn {query, response} ->
        text = line(SCPI.encode_response(response))
        {:ok, decoded} = SCPI.decode_response(query, text)
        close?(response, decoded) and line(SCPI.encode_response(decoded)) == text
      end),
      300
    )
  end

  test "property: a reading decodes to the double strtod gives its text (to the bit)" do
    # the text of a reading as a DAQ sends it (nine digits), as a short float, and as any run of
    # up to 17 digits with the point anywhere and an exponent: what Float.parse/1 makes of it
    digits = :proper_types.non_empty(:proper_types.list(:proper_types.integer(?0, ?9)))

    text_gen =
      :proper_types.oneof([
        :proper_types.bind(:proper_types.float(), &SCPI.number/1, false),
        :proper_types.bind(:proper_types.float(), &:erlang.float_to_binary(&1, [:short]), false),
        :proper_types.bind(
          {:proper_types.oneof(["", "+", "-"]), digits, digits, :proper_types.integer(-40, 40)},
          fn {sign, a, b, e} ->
            sign <>
              List.to_string(Enum.take(a, 9)) <>
              "." <>
              List.to_string(Enum.take(b, 8)) <>
              "E" <> Integer.to_string(e)
          end,
          false
        ),
        # exactly a DAQ's form (read in arithmetic), every two-digit exponent of either sign
        :proper_types.bind(
          {:proper_types.oneof(["+", "-"]), :proper_types.integer(0, 999_999_999),
           :proper_types.oneof(["+", "-"]), :proper_types.integer(0, 99),
           :proper_types.oneof(["E", "e"])},
          fn {sign, m, es, x, e} ->
            m = m |> Integer.to_string() |> String.pad_leading(9, "0")
            x = x |> Integer.to_string() |> String.pad_leading(2, "0")
            sign <> binary_part(m, 0, 1) <> "." <> binary_part(m, 1, 8) <> e <> es <> x
          end,
          false
        )
      ])

    assert_property(
      :proper.forall(text_gen, fn text ->
        {want, ""} = Float.parse(text)
        {:ok, [got]} = SCPI.decode_response({:meas_res?, [101]}, text <> "\n")
        got === want
      end),
      1_000
    )
  end

  test "property: a line of readings, whole or with one byte changed, reads as its fields' text" do
    # the DAQ's own form (read in one pass) mixed with others, then perhaps one byte anywhere
    # changed: what is read is what each field's text says (Float.parse/1), or an error —
    # never a value that no field says, never the right count from a damaged count
    field =
      :proper_types.oneof([
        :proper_types.bind(:proper_types.float(), &SCPI.number/1, false),
        :proper_types.bind(:proper_types.float(), &:erlang.float_to_binary(&1, [:short]), false)
      ])

    gen =
      {:proper_types.non_empty(:proper_types.list(field)), :proper_types.boolean(),
       :proper_types.non_neg_integer(), :proper_types.integer(0, 255)}

    assert_property(
      :proper.forall(gen, fn {fields, damage?, at, byte} ->
        text = Enum.join(fields, ",")
        at = rem(at, byte_size(text))

        text =
          if damage?,
            do:
              binary_part(text, 0, at) <>
                <<byte>> <> binary_part(text, at + 1, byte_size(text) - at - 1),
            else: text

        channels = Enum.to_list(101..(100 + length(fields)))

        case SCPI.decode_response({:meas_volt_dc?, channels}, text <> "\n") do
          {:ok, values} ->
            # as the line is read: a CR before its LF ends it (CR LF), whatever the CR was
            seen = String.replace_suffix(text, "\r", "")
            # (SCPI also reads "+.5", which Float.parse/1 reads as "+0.5")
            parsed =
              for field <- String.split(seen, ","),
                  do: Float.parse(Regex.replace(~r/^([+-]?)\./, field, "\\g{1}0."))

            parsed == Enum.map(values, &{&1, ""}) or {text, values, parsed}

          {:error, %SCPI.Error{}} ->
            damaged = text != Enum.join(fields, ",")
            damaged or {:refused_whole, text}
        end == true
      end),
      1_000
    )
  end

  test "property: lines cut anywhere come out whole, errors in place, buffer empty" do
    short_line =
      :proper_types.bind(
        :proper_types.list(:proper_types.integer(0x20, 0x7E)),
        &List.to_string/1,
        false
      )

    long_line =
      :proper_types.bind(:proper_types.integer(33, 80), &String.duplicate("z", &1), false)

    gen =
      {:proper_types.list(:proper_types.oneof([short_line, short_line, long_line])),
       :proper_types.list(:proper_types.integer(0, 400)), :proper_types.boolean()}

    assert_property(
      :proper.forall(gen, fn {lines, cuts, crlf} ->
        eol = if crlf, do: "\r\n", else: "\n"
        stream = Enum.map_join(lines, &(&1 <> eol))
        {chunks, last} = cut(stream, cuts)

        {out, d} =
          Enum.reduce(chunks ++ [last], {[], SCPI.new(max_line: 32)}, fn chunk, {acc, d} ->
            {out, d} = SCPI.feed(d, chunk)
            true = byte_size(d.buffer) <= 32
            {acc ++ out, d}
          end)

        expected =
          Enum.map(lines, fn l ->
            if byte_size(l <> eol) - 1 > 32, do: :too_long, else: l
          end)

        got =
          Enum.map(out, fn
            {:error, %Error{reason: :line_too_long}} -> :too_long
            l -> l
          end)

        got == expected and d.buffer == "" and not d.discarding
      end),
      200
    )
  end

  defp cut(stream, cuts) do
    Enum.reduce(cuts, {[], stream}, fn at, {chunks, rest} ->
      at = min(at, byte_size(rest))
      <<chunk::binary-size(at), rest::binary>> = rest
      {chunks ++ [chunk], rest}
    end)
  end

  test "property: random bytes never crash the decoders" do
    assert_property(
      :proper.forall({:proper_types.binary(), command_gen()}, fn {bytes, query} ->
        {out, d} = SCPI.feed(SCPI.new(max_line: 64), bytes)
        command = SCPI.decode_command(bytes)
        response = SCPI.decode_response(query, bytes)

        is_list(out) and byte_size(d.buffer) <= 64 and
          (match?({:ok, _}, command) or match?({:error, %Error{}}, command)) and
          (match?({:ok, _}, response) or match?({:error, %Error{}}, response))
      end),
      300
    )
  end

  # An independent reading of the grammar of PROTOCOLS.md §4, by regular expressions, so the
  # decoder's answers on arbitrary text can be checked: a line decodes, and to what, exactly
  # when this says so.
  @reference_headers [
    {~r/\A:?(MEAS|MEASURE):(VOLT|VOLTAGE):DC\?\z/i, :meas_volt_dc?, :list},
    {~r/\A:?(MEAS|MEASURE):(RES|RESISTANCE)\?\z/i, :meas_res?, :list},
    {~r/\A:?(ROUT|ROUTE):(CLOS|CLOSE)\z/i, :rout_clos, :list},
    {~r/\A:?(ROUT|ROUTE):OPEN\z/i, :rout_open, :list},
    {~r/\A:?(ROUT|ROUTE):(CLOS|CLOSE)\?\z/i, :rout_clos?, :list},
    {~r/\A:?(SYST|SYSTEM):(ERR|ERROR)(:NEXT)?\?\z/i, :syst_err?, :none},
    {~r/\A\*IDN\?\z/i, :idn?, :none},
    {~r/\A\*RST\z/i, :rst, :none},
    {~r/\A\*CLS\z/i, :cls, :none},
    {~r/\ACLAMP_PALLET\z/i, :clamp_pallet, :none},
    {~r/\ARELEASE_PALLET\z/i, :release_pallet, :none},
    {~r/\ASTATUS\?\z/i, :status?, :none},
    {~r/\APALLET\?\z/i, :pallet?, :none}
  ]

  defp reference(text) do
    text = Regex.replace(~r/\r?\n\z/, text, "", global: false)

    with true <- text =~ ~r/\A[\x20-\x7E\t]*\z/,
         [_, header, param] <-
           Regex.run(~r/\A[ \t]*([^ \t]+)(?:[ \t]+(.*?))?[ \t]*\z/s, text, capture: :all) |> pad(),
         {_, kind, shape} <- Enum.find(@reference_headers, fn {re, _, _} -> header =~ re end) do
      case {shape, param} do
        {:none, ""} -> {:ok, kind}
        {:list, param} -> with {:ok, chs} <- reference_list(param), do: {:ok, {kind, chs}}
        _ -> :error
      end
    else
      _ -> :error
    end
  end

  defp pad([all, header]), do: [all, header, ""]
  defp pad(other), do: other

  defp reference_list(param) do
    if param =~ ~r/\A\(@\d{3}(:\d{3})?(,\d{3}(:\d{3})?)*\)\z/ do
      items = param |> String.slice(2..-2//1) |> String.split(",")

      expanded =
        Enum.map(items, fn item ->
          case String.split(item, ":") |> Enum.map(&String.to_integer/1) do
            [a] ->
              if ok_channel(a), do: [a], else: nil

            [a, b] ->
              if ok_channel(a) and ok_channel(b) and a <= b and div(a, 100) == div(b, 100),
                do: Enum.to_list(a..b)
          end
        end)

      if Enum.all?(expanded), do: {:ok, Enum.concat(expanded)}, else: :error
    else
      :error
    end
  end

  defp ok_channel(ch), do: div(ch, 100) in 1..9 and rem(ch, 100) != 0

  defp agrees?(text) do
    case {SCPI.decode_command(text), reference(text)} do
      {{:ok, term}, {:ok, term}} -> true
      {{:error, %Error{}}, :error} -> true
      _ -> false
    end
  end

  test "the reference grammar agrees with the golden lines" do
    for {term, text} <- [{:idn?, "*IDN?"}, {{:rout_clos, [201, 202]}, ":route:close (@201:202)"}] do
      assert reference(text) == {:ok, term}
    end
  end

  test "property: a corrupted byte never passes for the command it was" do
    gen =
      :proper_types.bind(
        {command_gen(), :proper_types.integer(0, 1000), :proper_types.integer(1, 255)},
        fn {command, at, flip} -> {command, line(SCPI.encode_command(command)), at, flip} end,
        false
      )

    assert_property(
      :proper.forall(gen, fn {command, text, at, flip} ->
        at = rem(at, byte_size(text))
        <<before::binary-size(at), byte, rest::binary>> = text
        corrupted = <<before::binary, Bitwise.bxor(byte, flip), rest::binary>>
        # a decode to the same command is right only if the corrupted text is another way of
        # spelling it (letter case, `,` for `:` in a two-channel range, tab for space)
        agrees?(corrupted) and
          (SCPI.decode_command(corrupted) != {:ok, command} or
             reference(corrupted) == {:ok, command})
      end),
      600
    )
  end

  @vocabulary [
    "*IDN?",
    "*RST",
    "*CLS",
    "*",
    "SYST",
    "SYSTEM",
    "ERR",
    "ERROR",
    "NEXT",
    "?",
    ":",
    "MEAS",
    "MEASURE",
    "VOLT",
    "DC",
    "RES",
    "ROUT",
    "ROUTE",
    "CLOS",
    "CLOSE",
    "OPEN",
    "meas",
    "rout:clos",
    "Volt",
    "(@",
    "(",
    "@",
    ")",
    ",",
    "101",
    "116",
    "201",
    "199",
    "200",
    "999",
    "099",
    "1",
    "1016",
    " ",
    " ",
    "\t",
    "\r",
    "\n",
    "STATUS?",
    "PALLET?",
    "CLAMP_PALLET",
    "RELEASE_PALLET",
    "x",
    "0",
    "\e"
  ]

  test "property: text made of command words decodes exactly as the grammar says" do
    gen = :proper_types.list(:proper_types.oneof(@vocabulary))

    assert_property(
      :proper.forall(gen, fn words -> agrees?(Enum.join(words)) end),
      1500
    )
  end

  test "property: near-miss lines built from valid commands decode exactly as the grammar says" do
    gen =
      :proper_types.bind(
        {command_gen(), :proper_types.list(:proper_types.oneof(@vocabulary)),
         :proper_types.integer(0, 200)},
        fn {command, words, at} ->
          text = line(SCPI.encode_command(command))
          at = rem(at, byte_size(text))
          <<before::binary-size(at), rest::binary>> = text
          before <> Enum.join(words) <> rest
        end,
        false
      )

    assert_property(:proper.forall(gen, &agrees?/1), 600)
  end

  @keywords ~w(MEAS MEASURE MEASU VOLT VOLT? VOLTAGE VOLTAGE? DC DC? RES RES? RESISTANCE?
               ROUT ROUTE CLOS CLOS? CLOSE CLOSE? OPEN OPEN? SYST SYSTEM ERR ERR? ERROR?
               NEXT NEXT? *IDN? *RST *CLS STATUS? PALLET? CLAMP_PALLET RELEASE_PALLET meas clos?)

  test "property: commands with one keyword-level mistake decode exactly as the grammar says" do
    mutation =
      :proper_types.oneof([
        :drop,
        :dup,
        :chop,
        :query,
        :colon,
        {:replace, :proper_types.oneof(@keywords)},
        {:param, :proper_types.oneof(["", "(@101)", "(@101:116)", "1", "(@201,202)"])}
      ])

    gen = {command_gen(), mutation, :proper_types.integer(0, 3)}

    assert_property(
      :proper.forall(gen, fn {command, mutation, i} ->
        [header | param] =
          command
          |> SCPI.encode_command()
          |> line()
          |> String.trim()
          |> String.split(" ", parts: 2)

        keywords = String.split(header, ":")
        i = rem(i, length(keywords))

        {keywords, param} =
          case mutation do
            :drop -> {drop_keyword(keywords, i), param}
            :dup -> {List.insert_at(keywords, i, Enum.at(keywords, i)), param}
            :chop -> {List.update_at(keywords, i, &String.slice(&1, 0..-2//1)), param}
            :query -> {List.update_at(keywords, -1, &toggle_query/1), param}
            :colon -> {List.update_at(keywords, 0, &(":" <> &1)), param}
            {:replace, word} -> {List.replace_at(keywords, i, word), param}
            {:param, new} -> {keywords, if(new == "", do: [], else: [new])}
          end

        agrees?(Enum.join([Enum.join(keywords, ":") | param], " "))
      end),
      2000
    )
  end

  # leaves a node out as if it were optional, keeping the header a query if it was one
  defp drop_keyword(keywords, i) do
    dropped = List.delete_at(keywords, i)

    if dropped != [] and String.ends_with?(List.last(keywords), "?"),
      do: List.update_at(dropped, -1, &(String.trim_trailing(&1, "?") <> "?")),
      else: dropped
  end

  defp toggle_query(word) do
    if String.ends_with?(word, "?"), do: String.trim_trailing(word, "?"), else: word <> "?"
  end
end
