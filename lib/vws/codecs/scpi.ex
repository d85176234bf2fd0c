defmodule Vws.Codecs.SCPI do
  @moduledoc """
  The SCPI subset spoken on the HPIB (PROTOCOLS.md §4): commands and responses of the DAQs and
  of the hydraulic controller, as terms, plus an incremental LF line decoder. Pure: no
  processes, no I/O. The CEC's drivers encode commands and decode responses; the simulators do
  the opposite.

      iex> Vws.Codecs.SCPI.encode_command({:meas_volt_dc?, Enum.to_list(101..116)}) |> IO.iodata_to_binary()
      "MEAS:VOLT:DC? (@101:116)\\n"
      iex> Vws.Codecs.SCPI.decode_command("rout:clos (@201,203)\\n")
      {:ok, {:rout_clos, [201, 203]}}
      iex> Vws.Codecs.SCPI.encode_response([1.23456789, -0.5]) |> IO.iodata_to_binary()
      "+1.23456789E+00,-5.00000000E-01\\n"
      iex> Vws.Codecs.SCPI.decode_response({:meas_res?, [117]}, "+3.70012000E+02")
      {:ok, [370.012]}

  ## Commands

  | term                         | line                       | response                         |
  |------------------------------|----------------------------|----------------------------------|
  | `:idn?`                      | `*IDN?`                    | `t:idn/0`                        |
  | `:rst`                       | `*RST`                     | none                             |
  | `:cls`                       | `*CLS`                     | none                             |
  | `:syst_err?`                 | `SYST:ERR?`                | `{code, text}`: `+0,"No error"`  |
  | `{:meas_volt_dc?, channels}` | `MEAS:VOLT:DC? (@101:116)` | `[float]`, one per channel       |
  | `{:meas_res?, channels}`     | `MEAS:RES? (@117)`         | `[float]`, one per channel       |
  | `{:rout_clos, channels}`     | `ROUT:CLOS (@201)`         | none                             |
  | `{:rout_open, channels}`     | `ROUT:OPEN (@201)`         | none                             |
  | `{:rout_clos?, channels}`    | `ROUT:CLOS? (@201,202)`    | `[boolean]`: `1,0`               |
  | `:clamp_pallet`              | `CLAMP_PALLET`             | none (hydraulic controller)      |
  | `:release_pallet`            | `RELEASE_PALLET`           | none                             |
  | `:status?`                   | `STATUS?`                  | `:done \\| :executing \\| {:error, reason}` |
  | `:pallet?`                   | `PALLET?`                  | `t:pallet/0`                     |

  Decoding follows SCPI: headers are case-insensitive, each keyword in its short or its long
  form (`MEASure:VOLTage:DC?`, `ROUTe:CLOSe`, `SYSTem:ERRor[:NEXT]?`), a leading `:` is allowed,
  blanks (space, tab) separate the header from the parameter and may surround the line.
  Channels are three digits, slot 1–9 and channel 01–99; a list is `(@` items `)` with items
  `nnn` or `nnn:mmm` (ascending, one slot) separated by `,`, without blanks. Encoding writes
  short upper-case headers and folds runs of three or more consecutive channels into a range.
  Every encoded line ends in LF; decoders accept a line with or without its CR LF / LF.

  ## Responses

  Readings are written `+1.23456789E+00` (sign, nine significant digits, at least two exponent
  digits) and read in any SCPI number form. An overload reads `+9.90000000E+37`. `PALLET?` is
  answered (decision) `PALLET CLAMPED X=1 Y=1 F1=+5.00000000E+03 F2=+5.00000000E+03` or
  `PALLET NOT CLAMPED …`: the X and Y switches and the two clamp forces in newtons.
  A response says nothing of its own type, so `decode_response/2` takes the query it answers.

  ## Lines

  `new/1` and `feed/2` cut a byte stream into lines at LF (dropping one CR before it). A line
  longer than `:max_line` (default 4096 bytes) is discarded up to its LF and reported once as
  `{:error, %Vws.Codecs.SCPI.Error{reason: :line_too_long}}`; the decoder never holds more than
  `max_line` bytes.
  """

  alias Vws.Codecs.SCPI.Error

  @default_max_line 4096
  @overload 9.9e37
  @error_line_cut 80

  @type channel :: 101..999
  @type command ::
          :idn?
          | :rst
          | :cls
          | :syst_err?
          | {:meas_volt_dc? | :meas_res? | :rout_clos | :rout_open | :rout_clos?, [channel, ...]}
          | :clamp_pallet
          | :release_pallet
          | :status?
          | :pallet?
  @type idn :: %{
          manufacturer: String.t(),
          model: String.t(),
          serial: String.t(),
          firmware: String.t()
        }
  @type pallet :: %{
          clamped: boolean,
          x: boolean,
          y: boolean,
          force1_n: float,
          force2_n: float
        }
  @type response ::
          [float]
          | [boolean]
          | {integer, String.t()}
          | idn
          | :done
          | :executing
          | {:error, String.t()}
          | pallet

  @typedoc "An incremental line decoder."
  @type t :: %__MODULE__{buffer: binary, max_line: pos_integer, discarding: boolean}
  defstruct buffer: "", max_line: @default_max_line, discarding: false

  # Header keywords: each {short, long}; the whole header is a list of them.
  @headers [
    {[{"MEAS", "MEASURE"}, {"VOLT", "VOLTAGE"}, {"DC?", "DC?"}], :meas_volt_dc?},
    {[{"MEAS", "MEASURE"}, {"RES?", "RESISTANCE?"}], :meas_res?},
    {[{"ROUT", "ROUTE"}, {"CLOS", "CLOSE"}], :rout_clos},
    {[{"ROUT", "ROUTE"}, {"OPEN", "OPEN"}], :rout_open},
    {[{"ROUT", "ROUTE"}, {"CLOS?", "CLOSE?"}], :rout_clos?},
    {[{"SYST", "SYSTEM"}, {"ERR?", "ERROR?"}], :syst_err?},
    {[{"SYST", "SYSTEM"}, {"ERR", "ERROR"}, {"NEXT?", "NEXT?"}], :syst_err?}
  ]

  @bare %{
    "*IDN?" => :idn?,
    "*RST" => :rst,
    "*CLS" => :cls,
    "CLAMP_PALLET" => :clamp_pallet,
    "RELEASE_PALLET" => :release_pallet,
    "STATUS?" => :status?,
    "PALLET?" => :pallet?
  }

  @bare_lines Map.new(@bare, fn {line, term} -> {term, line} end)

  @list_lines %{
    meas_volt_dc?: "MEAS:VOLT:DC?",
    meas_res?: "MEAS:RES?",
    rout_clos: "ROUT:CLOS",
    rout_open: "ROUT:OPEN",
    rout_clos?: "ROUT:CLOS?"
  }

  @list_commands Map.keys(@list_lines)

  ## Commands

  @doc """
  Encodes a command as one line, LF included. Raises `ArgumentError` for a term that is not a
  command or an empty or invalid channel list (a programming error).
  """
  @spec encode_command(command) :: iodata
  def encode_command(:syst_err?), do: "SYST:ERR?\n"

  def encode_command(command) when is_map_key(@bare_lines, command),
    do: [Map.fetch!(@bare_lines, command), ?\n]

  def encode_command({command, [_ | _] = channels}) when command in @list_commands do
    [Map.fetch!(@list_lines, command), " ", encode_channels(channels), ?\n]
  end

  def encode_command(other),
    do: raise(ArgumentError, "not an SCPI command of our subset: #{inspect(other)}")

  @doc "Decodes one command line (its CR LF / LF optional)."
  @spec decode_command(binary) :: {:ok, command} | {:error, Error.t()}
  def decode_command(line) when is_binary(line) do
    line = strip_terminator(line)

    with :ok <- printable(line),
         trimmed when trimmed != "" <- trim_blanks(line),
         {header, parameter} <- split_header(trimmed),
         {:ok, kind} <- header(String.upcase(header)),
         {:ok, command} <- parameter(kind, parameter) do
      {:ok, command}
    else
      "" -> error(:empty, line)
      {:error, reason} -> error(reason, line)
    end
  end

  defp trim_blanks(text), do: String.replace(text, ~r/\A[ \t]+|[ \t]+\z/, "")

  defp split_header(text) do
    case :binary.match(text, [" ", "\t"]) do
      {pos, 1} ->
        <<header::binary-size(pos), _blank, rest::binary>> = text
        {header, trim_blanks(rest)}

      :nomatch ->
        {text, ""}
    end
  end

  defp header(header) do
    case Map.fetch(@bare, header) do
      {:ok, kind} ->
        {:ok, kind}

      :error ->
        keywords =
          case header do
            ":" <> rest -> String.split(rest, ":")
            _ -> String.split(header, ":")
          end

        Enum.find_value(@headers, {:error, :undefined_header}, fn {forms, kind} ->
          if keywords_match?(keywords, forms), do: {:ok, kind}
        end)
    end
  end

  defp keywords_match?(keywords, forms) when length(keywords) == length(forms) do
    keywords
    |> Enum.zip(forms)
    |> Enum.all?(fn {word, {short, long}} -> word == short or word == long end)
  end

  defp keywords_match?(_keywords, _forms), do: false

  defp parameter(kind, "") when kind in @list_commands, do: {:error, :missing_parameter}

  defp parameter(kind, text) when kind in @list_commands do
    with {:ok, channels} <- decode_channels(text), do: {:ok, {kind, channels}}
  end

  defp parameter(kind, ""), do: {:ok, kind}
  defp parameter(_kind, _text), do: {:error, :unexpected_parameter}

  ## Channel lists

  defp encode_channels(channels) do
    Enum.each(channels, fn channel ->
      valid_channel?(channel) ||
        raise ArgumentError, "not a channel (slot 1-9, channel 01-99): #{inspect(channel)}"
    end)

    items = channels |> runs() |> Enum.map(&run_text/1) |> Enum.intersperse(",")
    ["(@", items, ")"]
  end

  # Consecutive ascending channels of one slot, as {first, last} runs.
  defp runs(channels) do
    channels
    |> Enum.reduce([], fn
      ch, [{first, last} | rest] when ch == last + 1 and div(ch, 100) == div(first, 100) ->
        [{first, ch} | rest]

      ch, acc ->
        [{ch, ch} | acc]
    end)
    |> Enum.reverse()
    |> Enum.flat_map(fn
      {first, last} when last - first >= 2 -> [{first, last}]
      {first, last} -> Enum.map(first..last, &{&1, &1})
    end)
  end

  defp run_text({ch, ch}), do: Integer.to_string(ch)
  defp run_text({first, last}), do: [Integer.to_string(first), ?:, Integer.to_string(last)]

  defp decode_channels("(@" <> rest) do
    with {:ok, body} <- closing(rest) do
      body
      |> String.split(",")
      |> Enum.reduce_while({:ok, []}, fn item, {:ok, acc} ->
        case channel_item(item) do
          {:ok, channels} -> {:cont, {:ok, [channels | acc]}}
          error -> {:halt, error}
        end
      end)
      |> case do
        {:ok, lists} -> {:ok, lists |> Enum.reverse() |> Enum.concat()}
        error -> error
      end
    end
  end

  defp decode_channels(_text), do: {:error, :bad_channel_list}

  defp closing(rest) do
    size = byte_size(rest) - 1

    case rest do
      <<body::binary-size(size), ")">> when size > 0 -> {:ok, body}
      _ -> {:error, :bad_channel_list}
    end
  end

  defp channel_item(<<a::binary-size(3), ":", b::binary-size(3)>>) do
    with {:ok, first} <- channel_number(a),
         {:ok, last} <- channel_number(b) do
      if first <= last and div(first, 100) == div(last, 100),
        do: {:ok, Enum.to_list(first..last)},
        else: {:error, :channel_out_of_range}
    end
  end

  defp channel_item(<<a::binary-size(3)>>) do
    with {:ok, ch} <- channel_number(a), do: {:ok, [ch]}
  end

  defp channel_item(_item), do: {:error, :bad_channel_list}

  defp channel_number(<<d1, d2, d3>> = digits)
       when d1 in ?0..?9 and d2 in ?0..?9 and d3 in ?0..?9 do
    ch = String.to_integer(digits)
    if valid_channel?(ch), do: {:ok, ch}, else: {:error, :channel_out_of_range}
  end

  defp channel_number(_text), do: {:error, :bad_channel_list}

  defp valid_channel?(ch), do: is_integer(ch) and ch in 101..999 and rem(ch, 100) != 0

  ## Responses

  @doc """
  Encodes a response as one line, LF included: a list of numbers as readings, a list of
  booleans as `1`/`0` states, `{code, text}` as an error-queue entry, an `t:idn/0` map,
  `:done`/`:executing`/`{:error, reason}` as a hydraulic status, a `t:pallet/0` map.
  """
  @spec encode_response(response) :: iodata
  def encode_response([first | _] = states) when is_boolean(first) do
    [states |> Enum.map(&if(&1, do: "1", else: "0")) |> Enum.intersperse(","), ?\n]
  end

  def encode_response([_ | _] = readings) do
    [readings |> Enum.map(&number/1) |> Enum.intersperse(","), ?\n]
  end

  def encode_response({code, text}) when is_integer(code) and is_binary(text) do
    sign = if code >= 0, do: "+", else: ""
    [sign, Integer.to_string(code), ?,, ?", String.replace(text, "\"", "\"\""), ?", ?\n]
  end

  def encode_response(%{manufacturer: _, model: _, serial: _, firmware: _} = idn) do
    [Enum.intersperse([idn.manufacturer, idn.model, idn.serial, idn.firmware], ","), ?\n]
  end

  def encode_response(:done), do: "DONE\n"
  def encode_response(:executing), do: "EXECUTING\n"
  def encode_response({:error, reason}) when is_binary(reason), do: ["ERROR ", reason, ?\n]

  def encode_response(%{clamped: clamped, x: x, y: y, force1_n: f1, force2_n: f2}) do
    [
      if(clamped, do: "PALLET CLAMPED", else: "PALLET NOT CLAMPED"),
      " X=",
      bit(x),
      " Y=",
      bit(y),
      " F1=",
      number(f1),
      " F2=",
      number(f2),
      ?\n
    ]
  end

  def encode_response(other),
    do: raise(ArgumentError, "not an SCPI response of our subset: #{inspect(other)}")

  defp bit(true), do: "1"
  defp bit(false), do: "0"

  @doc """
  A reading in SCPI form, `+1.23456789E+00`.

      iex> Vws.Codecs.SCPI.number(9.9e37)
      "+9.90000000E+37"
  """
  @spec number(number) :: binary
  def number(value) when is_number(value) do
    text = :erlang.float_to_binary(value * 1.0, scientific: 8)
    text = String.replace(text, "e", "E")
    if String.starts_with?(text, "-"), do: text, else: "+" <> text
  end

  @doc "What an overloaded or open input reads (HP/Agilent convention): 9.9e37."
  @spec overload() :: float
  def overload, do: @overload

  @doc "Whether a command is answered by a response line."
  @spec response?(command) :: boolean
  def response?(command) when command in [:idn?, :syst_err?, :status?, :pallet?], do: true
  def response?({command, _}) when command in [:meas_volt_dc?, :meas_res?, :rout_clos?], do: true
  def response?(_command), do: false

  @doc """
  Whether a command may be sent again when its answer was lost or damaged, with the same
  effect as once: the queries that only read (not `SYST:ERR?`, which takes an error off the
  queue) and the relay settings (`ROUT:CLOS`/`ROUT:OPEN` set a state, they do not toggle it).
  `*RST`, `*CLS` and the hydraulic controller's `CLAMP_PALLET`/`RELEASE_PALLET` are not.
  """
  @spec repeatable?(command) :: boolean
  def repeatable?(command) when command in [:idn?, :status?, :pallet?], do: true

  def repeatable?({command, _})
      when command in [:meas_volt_dc?, :meas_res?, :rout_clos?, :rout_clos, :rout_open],
      do: true

  def repeatable?(_command), do: false

  @doc "Decodes the response line answering `query` (its CR LF / LF optional)."
  @spec decode_response(command, binary) :: {:ok, response} | {:error, Error.t()}
  def decode_response(query, line) when is_binary(line) do
    line = strip_terminator(line)

    result =
      cond do
        not response?(query) -> {:error, :no_response}
        (readings = readings_at_once(query, line)) != :slow -> readings
        true -> with :ok <- printable(line), do: response(query, line)
      end

    case result do
      {:ok, response} -> {:ok, response}
      {:error, reason} -> error(reason, line)
      :error -> error(:bad_response, line)
    end
  end

  defp response({kind, channels}, line) when kind in [:meas_volt_dc?, :meas_res?] do
    fields = :binary.split(line, ",", [:global])

    if length(fields) == length(channels),
      do: all_numbers(fields, []),
      else: :error
  end

  defp response({:rout_clos?, channels}, line) do
    fields = String.split(line, ",")

    if length(fields) == length(channels) do
      all_ok(fields, fn
        "1" -> {:ok, true}
        "0" -> {:ok, false}
        _ -> :error
      end)
    else
      :error
    end
  end

  defp response(:syst_err?, line) do
    with [code, quoted] <- String.split(line, ",", parts: 2),
         {:ok, code} <- parse_integer(code),
         {:ok, text} <- unquote_string(quoted) do
      {:ok, {code, text}}
    else
      _ -> :error
    end
  end

  defp response(:idn?, line) do
    case String.split(line, ",") do
      [manufacturer, model, serial, firmware] ->
        {:ok, %{manufacturer: manufacturer, model: model, serial: serial, firmware: firmware}}

      _ ->
        :error
    end
  end

  defp response(:status?, "DONE"), do: {:ok, :done}
  defp response(:status?, "EXECUTING"), do: {:ok, :executing}
  defp response(:status?, "ERROR " <> reason) when reason != "", do: {:ok, {:error, reason}}
  defp response(:status?, _line), do: :error

  defp response(:pallet?, line) do
    {clamped, rest} =
      case line do
        "PALLET CLAMPED " <> rest -> {true, rest}
        "PALLET NOT CLAMPED " <> rest -> {false, rest}
        _ -> {nil, ""}
      end

    with true <- is_boolean(clamped),
         ["X=" <> x, "Y=" <> y, "F1=" <> f1, "F2=" <> f2] <- String.split(rest, " "),
         {:ok, x} <- parse_bit(x),
         {:ok, y} <- parse_bit(y),
         {:ok, f1} <- parse_number(f1),
         {:ok, f2} <- parse_number(f2) do
      {:ok, %{clamped: clamped, x: x, y: y, force1_n: f1, force2_n: f2}}
    else
      _ -> :error
    end
  end

  defp all_ok(fields, parse), do: all_ok(fields, parse, [])

  defp all_ok([field | rest], parse, acc) do
    case parse.(field) do
      {:ok, value} -> all_ok(rest, parse, [value | acc])
      :error -> :error
    end
  end

  defp all_ok([], _parse, acc), do: {:ok, :lists.reverse(acc)}

  defguardp digit(d) when d in ?0..?9

  @powers_of_ten List.to_tuple(for n <- 0..22, do: :math.pow(10, n))

  # A line of readings all in the form every DAQ reading of ours has ("+1.23456789E+00",
  # number/1), read in one pass: each matched byte is a digit, sign, point, E or comma, so the
  # line is printable without looking at it again, and no field is split off. Anything else —
  # another form, a damaged byte, a count that differs, a scale beyond Clinger's fast path —
  # is :slow, and the line is read field by field below, to the same values or the same error.
  defp readings_at_once({kind, channels}, line) when kind in [:meas_volt_dc?, :meas_res?],
    do: readings_at_once(line, length(channels), [])

  defp readings_at_once(_query, _line), do: :slow

  defp readings_at_once(
         <<s, i, ?., f1, f2, f3, f4, f5, f6, f7, f8, e, es, x1, x2, rest::binary>>,
         n,
         acc
       )
       when n > 0 and s in [?+, ?-] and digit(i) and digit(f1) and digit(f2) and digit(f3) and
              digit(f4) and digit(f5) and digit(f6) and digit(f7) and digit(f8) and
              e in [?E, ?e] and es in [?+, ?-] and digit(x1) and digit(x2) do
    case fast_number(s, i, f1, f2, f3, f4, f5, f6, f7, f8, es, x1, x2) do
      :slow ->
        :slow

      value ->
        case rest do
          <<>> when n == 1 -> {:ok, :lists.reverse([value | acc])}
          <<?,, rest::binary>> when n > 1 -> readings_at_once(rest, n - 1, [value | acc])
          _ -> :slow
        end
    end
  end

  defp readings_at_once(_line, _n, _acc), do: :slow

  # the nine digits and the exponent in arithmetic, no binaries: to_float/4's fast path, the
  # same value to the bit; :slow when the scale is beyond it
  defp fast_number(s, i, f1, f2, f3, f4, f5, f6, f7, f8, es, x1, x2) do
    m =
      (i - ?0) * 100_000_000 + (f1 - ?0) * 10_000_000 + (f2 - ?0) * 1_000_000 +
        (f3 - ?0) * 100_000 + (f4 - ?0) * 10_000 + (f5 - ?0) * 1_000 + (f6 - ?0) * 100 +
        (f7 - ?0) * 10 + (f8 - ?0)

    x = (x1 - ?0) * 10 + (x2 - ?0)
    scale = if(es == ?-, do: -x, else: x) - 8

    if scale in -22..22 do
      value =
        if scale >= 0,
          do: m * 1.0 * elem(@powers_of_ten, scale),
          else: m * 1.0 / elem(@powers_of_ten, -scale)

      if s == ?-, do: -value, else: value
    else
      :slow
    end
  end

  # all_ok(fields, &parse_number/1) without the call through a fun: a poll reads 17 of them
  defp all_numbers([field | rest], acc) do
    case parse_number(field) do
      {:ok, value} -> all_numbers(rest, [value | acc])
      :error -> :error
    end
  end

  defp all_numbers([], acc), do: {:ok, :lists.reverse(acc)}

  defp parse_bit("1"), do: {:ok, true}
  defp parse_bit("0"), do: {:ok, false}
  defp parse_bit(_), do: :error

  # SCPI NR1/NR2/NR3: [+-] digits [. digits] [E [+-] digits], or [+-] . digits [...]; at
  # most 4 exponent digits. Read by matching bytes (a DAQ #1 poll reads 17 numbers: a regex
  # and Float.parse/1 each were most of the CEC's cost of decoding it).
  # the form every reading of ours has (number/1: "+1.23456789E+00"), matched at once
  defp parse_number(<<s, i, ?., f1, f2, f3, f4, f5, f6, f7, f8, e, es, x1, x2>> = text)
       when s in [?+, ?-] and digit(i) and digit(f1) and digit(f2) and digit(f3) and
              digit(f4) and digit(f5) and digit(f6) and digit(f7) and digit(f8) and
              e in [?E, ?e] and es in [?+, ?-] and digit(x1) and digit(x2) do
    case fast_number(s, i, f1, f2, f3, f4, f5, f6, f7, f8, es, x1, x2) do
      :slow -> to_float(binary_part(text, 0, 1), <<i>>, binary_part(text, 3, 8), <<es, x1, x2>>)
      value -> {:ok, value}
    end
  end

  defp parse_number(text) do
    {sign, rest} =
      case text do
        <<s, rest::binary>> when s in [?+, ?-] -> {<<s>>, rest}
        rest -> {"", rest}
      end

    {int, rest} = digits(rest)

    {frac, rest} =
      case rest do
        "." <> rest -> digits(rest)
        rest -> {"", rest}
      end

    with false <- int == "" and frac == "",
         {:ok, exp} <- exponent_part(rest) do
      to_float(sign, int, frac, exp)
    else
      _ -> :error
    end
  end

  # Up to 15 digits and a scale within 10^±22: the digits and the power of ten are both exact
  # doubles, so one multiplication or division rounds correctly, as strtod does (Clinger's fast
  # path) — a DAQ's "+1.23456789E+00" is always this case, and binary_to_float/1 takes ~2 µs.
  defp to_float(sign, int, frac, exp) do
    digits = int <> frac
    scale = if(exp == "", do: 0, else: String.to_integer(exp)) - byte_size(frac)

    if byte_size(digits) <= 15 and scale in -22..22 do
      m = :erlang.binary_to_integer(digits) * 1.0

      value =
        if scale >= 0,
          do: m * elem(@powers_of_ten, scale),
          else: m / elem(@powers_of_ten, -scale)

      {:ok, if(sign == "-", do: -value, else: value)}
    else
      float_text = sign <> default(int, "0") <> "." <> default(frac, "0") <> exponent(exp)

      try do
        {:ok, :erlang.binary_to_float(float_text)}
      rescue
        # out of a double's range
        ArgumentError -> :error
      end
    end
  end

  defp digits(text), do: digits(text, 0)

  # eight at a time where it can: a DAQ's readings have eight digits after the point

  defp digits(text, n) do
    case text do
      <<_::binary-size(n), a, b, c, d, e, f, g, h, _::binary>>
      when digit(a) and digit(b) and digit(c) and digit(d) and digit(e) and digit(f) and
             digit(g) and digit(h) ->
        digits(text, n + 8)

      <<_::binary-size(n), d, _::binary>> when digit(d) ->
        digits(text, n + 1)

      <<ds::binary-size(n), rest::binary>> ->
        {ds, rest}
    end
  end

  defp exponent_part(""), do: {:ok, ""}

  defp exponent_part(<<e, rest::binary>>) when e in [?e, ?E] do
    {sign, rest} =
      case rest do
        <<s, rest::binary>> when s in [?+, ?-] -> {<<s>>, rest}
        rest -> {"", rest}
      end

    case digits(rest) do
      {ds, ""} when byte_size(ds) in 1..4 -> {:ok, sign <> ds}
      _ -> :error
    end
  end

  defp exponent_part(_rest), do: :error

  defp default("", value), do: value
  defp default(text, _value), do: text

  defp exponent(""), do: ""
  defp exponent(exp), do: "e" <> exp

  defp parse_integer(text) do
    if text =~ ~r/\A[+-]?\d{1,10}\z/, do: {:ok, String.to_integer(text)}, else: :error
  end

  defp unquote_string(<<?", rest::binary>>) when byte_size(rest) >= 1 do
    size = byte_size(rest) - 1
    <<body::binary-size(size), last>> = rest

    if last == ?" and not String.match?(String.replace(body, "\"\"", ""), ~r/"/),
      do: {:ok, String.replace(body, "\"\"", "\"")},
      else: :error
  end

  defp unquote_string(_text), do: :error

  ## Line decoder

  @doc "A line decoder; option `:max_line` bounds a line (default #{@default_max_line} bytes)."
  @spec new(keyword) :: t
  def new(opts \\ []) do
    max = Keyword.get(opts, :max_line, @default_max_line)

    unless is_integer(max) and max > 0,
      do: raise(ArgumentError, "max_line must be a positive integer, got #{inspect(max)}")

    %__MODULE__{max_line: max}
  end

  @doc """
  Gives the decoder bytes; returns the complete lines (without CR LF / LF) and errors, in order.

      iex> {lines, decoder} = Vws.Codecs.SCPI.feed(Vws.Codecs.SCPI.new(), "*IDN?\\nMEAS:RES? (@1")
      iex> lines
      ["*IDN?"]
      iex> {lines, _decoder} = Vws.Codecs.SCPI.feed(decoder, "17)\\r\\n")
      iex> lines
      ["MEAS:RES? (@117)"]
  """
  @spec feed(t, binary) :: {[binary | {:error, Error.t()}], t}
  def feed(%__MODULE__{} = decoder, bytes) when is_binary(bytes) do
    do_feed(decoder, bytes, [])
  end

  defp do_feed(decoder, bytes, acc) do
    case :binary.match(bytes, "\n") do
      {pos, 1} ->
        <<chunk::binary-size(pos), ?\n, rest::binary>> = bytes

        cond do
          decoder.discarding ->
            do_feed(%{decoder | discarding: false}, rest, acc)

          byte_size(decoder.buffer) + pos > decoder.max_line ->
            do_feed(%{decoder | buffer: ""}, rest, [too_long(decoder) | acc])

          true ->
            line = strip_cr(decoder.buffer <> chunk)
            do_feed(%{decoder | buffer: ""}, rest, [line | acc])
        end

      :nomatch ->
        cond do
          decoder.discarding ->
            {Enum.reverse(acc), decoder}

          byte_size(decoder.buffer) + byte_size(bytes) > decoder.max_line ->
            {Enum.reverse([too_long(decoder) | acc]), %{decoder | buffer: "", discarding: true}}

          true ->
            {Enum.reverse(acc), %{decoder | buffer: decoder.buffer <> bytes}}
        end
    end
  end

  defp too_long(decoder), do: {:error, %Error{reason: :line_too_long, max: decoder.max_line}}

  ## Helpers

  defp strip_terminator(line) do
    size = byte_size(line) - 1

    case line do
      <<body::binary-size(size), ?\n>> -> strip_cr(body)
      _ -> line
    end
  end

  defp strip_cr(line) do
    size = byte_size(line) - 1

    case line do
      <<body::binary-size(size), ?\r>> -> body
      _ -> line
    end
  end

  defp printable(line) do
    if printable?(line), do: :ok, else: {:error, :bad_character}
  end

  defguardp printable_byte(c) when c in 0x20..0x7E or c == ?\t

  # eight bytes at a time where it can (a poll's answer is ~270 bytes)
  # sixteen, then eight bytes a step where it can (a step costs what a byte would)
  defp printable?(<<a, b, c, d, e, f, g, h, i, j, k, l, m, n, o, p, rest::binary>>)
       when printable_byte(a) and printable_byte(b) and printable_byte(c) and printable_byte(d) and
              printable_byte(e) and printable_byte(f) and printable_byte(g) and printable_byte(h) and
              printable_byte(i) and printable_byte(j) and printable_byte(k) and printable_byte(l) and
              printable_byte(m) and printable_byte(n) and printable_byte(o) and printable_byte(p),
       do: printable?(rest)

  defp printable?(<<a, b, c, d, e, f, g, h, rest::binary>>)
       when printable_byte(a) and printable_byte(b) and printable_byte(c) and printable_byte(d) and
              printable_byte(e) and
              printable_byte(f) and printable_byte(g) and printable_byte(h),
       do: printable?(rest)

  defp printable?(<<c, rest::binary>>) when printable_byte(c), do: printable?(rest)
  defp printable?(<<>>), do: true
  defp printable?(_), do: false

  defp error(reason, line) do
    {:error,
     %Error{reason: reason, line: binary_part(line, 0, min(byte_size(line), @error_line_cut))}}
  end
end
