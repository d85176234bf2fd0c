defmodule Vws.Codecs.RFC2217 do
  @moduledoc """
  Telnet (RFC 854/855) with the COM Port Control Option (RFC 2217): a pure codec for
  `Vws.Links.Transport.RFC2217`, no process, no I/O.

  **Data** goes with every IAC (255) doubled, both ways (`escape/1`; the decoder undoes it).
  **Negotiation**: `IAC WILL|WONT|DO|DONT option` (`option/2`). **Subnegotiation**:
  `IAC SB option payload IAC SE`, IACs in the payload doubled (`subneg/2`). COM-PORT-OPTION is
  option 44; the client's commands are 1–12 and the server answers each with the same command
  plus 100 (`com_port/1` encodes a client's, `decode/2` reads the server's):

  | command | client → server | server → client | value |
  |---------|-----------------|-----------------|-------|
  | SET-BAUDRATE | 1 | 101 | 4 bytes, big-endian (0: ask) |
  | SET-DATASIZE | 2 | 102 | 1 byte, 5–8 (0: ask) |
  | SET-PARITY | 3 | 103 | 1 NONE, 2 ODD, 3 EVEN, 4 MARK, 5 SPACE (0: ask) |
  | SET-STOPSIZE | 4 | 104 | 1 one, 2 two, 3 one and a half (0: ask) |
  | SET-CONTROL | 5 | 105 | 1 no flow control, 2 XON/XOFF, 3 RTS/CTS (0: ask) |
  | NOTIFY-LINESTATE | 6 | 106 | the line-state byte (bit 1 overrun, 2 parity, 3 framing, 4 break) |
  | NOTIFY-MODEMSTATE | 7 | 107 | the modem-state byte (bit 7 carrier, 5 DSR, 4 CTS) |
  | SET-LINESTATE-MASK | 10 | 110 | 1 byte |
  | SET-MODEMSTATE-MASK | 11 | 111 | 1 byte |

      iex> IO.iodata_to_binary(Vws.Codecs.RFC2217.com_port({:baud, 4800}))
      <<255, 250, 44, 1, 0, 0, 18, 192, 255, 240>>
      iex> IO.iodata_to_binary(Vws.Codecs.RFC2217.escape(<<1, 255, 2>>))
      <<1, 255, 255, 2>>
      iex> {events, _} = Vws.Codecs.RFC2217.decode(Vws.Codecs.RFC2217.decoder(), <<?A, 255, 255, 255, 251, 44, 255, 250, 44, 103, 3, 255, 240>>)
      iex> events
      [{:data, <<?A, 255>>}, {:will, 44}, {:com_port, {:parity, :even}}]

  The decoder takes bytes split anywhere and never raises: an unknown command byte after IAC
  is `{:command, byte}`, a subnegotiation longer than #{64} bytes is dropped
  (`{:error, :subneg_too_long}`), one of another option is `{:subneg, option, payload}`, a
  COM-PORT-OPTION reply it cannot read is `{:com_port, {:unknown, command, payload}}`.
  """

  @iac 255
  @t_dont 254
  @t_do 253
  @wont 252
  @will 251
  @sb 250
  @se 240
  @com_port 44
  @max_subneg 64

  @doc "The COM-PORT-OPTION option number."
  def com_port_option, do: @com_port

  @type setting ::
          {:baud, non_neg_integer}
          | {:data_size, 0..8}
          | {:parity, :ask | :none | :odd | :even | :mark | :space}
          | {:stop_size, :ask | 1 | 2 | :one_and_half}
          | {:control, :ask | :none | :xonxoff | :rtscts | atom}
          | {:linestate, byte}
          | {:modemstate, byte}
          | {:linestate_mask, byte}
          | {:modemstate_mask, byte}

  @type event ::
          {:data, binary}
          | {:will | :wont | :do | :dont, byte}
          | {:com_port, setting | {:unknown, byte, binary}}
          | {:subneg, byte, binary}
          | {:command, byte}
          | {:error, :subneg_too_long}

  @doc "Data with every IAC doubled."
  @spec escape(iodata) :: iodata
  def escape(data) do
    data = IO.iodata_to_binary(data)

    case :binary.match(data, <<@iac>>) do
      :nomatch -> data
      _ -> :binary.replace(data, <<@iac>>, <<@iac, @iac>>, [:global])
    end
  end

  @doc "A negotiation: `IAC WILL|WONT|DO|DONT option`."
  @spec option(:will | :wont | :do | :dont, byte) :: binary
  def option(verb, opt), do: <<@iac, verb_byte(verb), opt>>

  @doc "A subnegotiation of `option` (payload IAC-doubled)."
  @spec subneg(byte, iodata) :: iodata
  def subneg(opt, payload), do: [<<@iac, @sb, opt>>, escape(payload), <<@iac, @se>>]

  @doc "A client's COM-PORT-OPTION command."
  @spec com_port(setting) :: iodata
  def com_port({key, value}) do
    {command, payload} = setting(key, value)
    subneg(@com_port, [command, payload])
  end

  defp setting(:baud, baud), do: {1, <<baud::32>>}
  defp setting(:data_size, n), do: {2, <<n>>}
  defp setting(:parity, p), do: {3, <<parity_byte(p)>>}
  defp setting(:stop_size, s), do: {4, <<stop_byte(s)>>}
  defp setting(:control, c), do: {5, <<control_byte(c)>>}
  defp setting(:linestate_mask, m), do: {10, <<m>>}
  defp setting(:modemstate_mask, m), do: {11, <<m>>}

  @parities [ask: 0, none: 1, odd: 2, even: 3, mark: 4, space: 5]
  @stops [ask: 0, "1": 1, "2": 2, one_and_half: 3]
  # SET-CONTROL's outbound flow control values (1–3) and the ask (0)
  @controls [ask: 0, none: 1, xonxoff: 2, rtscts: 3]

  defp parity_byte(p), do: Keyword.fetch!(@parities, p)
  defp stop_byte(1), do: 1
  defp stop_byte(2), do: 2
  defp stop_byte(s), do: Keyword.fetch!(@stops, s)
  defp control_byte(c), do: Keyword.fetch!(@controls, c)

  defp verb_byte(:will), do: @will
  defp verb_byte(:wont), do: @wont
  defp verb_byte(:do), do: @t_do
  defp verb_byte(:dont), do: @t_dont

  ## Decoding

  @doc "A fresh decoder."
  @spec decoder() :: map
  def decoder, do: %{state: :data, sb: [], sb_size: 0}

  @doc "Takes received bytes (split anywhere): `{events, decoder}`, adjacent data merged."
  @spec decode(map, binary) :: {[event], map}
  def decode(d, bytes) when is_binary(bytes) do
    {events, d} = step(bytes, d, [])
    {merge(Enum.reverse(events)), d}
  end

  defp merge([{:data, a}, {:data, b} | rest]), do: merge([{:data, a <> b} | rest])
  defp merge([e | rest]), do: [e | merge(rest)]
  defp merge([]), do: []

  defp step(<<>>, d, acc), do: {acc, d}

  # data: the run up to the next IAC in one piece
  defp step(bytes, %{state: :data} = d, acc) do
    case :binary.match(bytes, <<@iac>>) do
      :nomatch ->
        {[{:data, bytes} | acc], d}

      {at, 1} ->
        <<run::binary-size(at), _iac, rest::binary>> = bytes
        acc = if run == "", do: acc, else: [{:data, run} | acc]
        step(rest, %{d | state: :iac}, acc)
    end
  end

  defp step(<<@iac, rest::binary>>, %{state: :iac} = d, acc),
    do: step(rest, %{d | state: :data}, [{:data, <<@iac>>} | acc])

  defp step(<<verb, rest::binary>>, %{state: :iac} = d, acc)
       when verb in [@will, @wont, @t_do, @t_dont],
       do: step(rest, %{d | state: {:verb, verb}}, acc)

  defp step(<<@sb, rest::binary>>, %{state: :iac} = d, acc),
    do: step(rest, %{d | state: :sb, sb: [], sb_size: 0}, acc)

  defp step(<<command, rest::binary>>, %{state: :iac} = d, acc),
    do: step(rest, %{d | state: :data}, [{:command, command} | acc])

  defp step(<<opt, rest::binary>>, %{state: {:verb, verb}} = d, acc),
    do: step(rest, %{d | state: :data}, [{verb_atom(verb), opt} | acc])

  defp step(<<@iac, rest::binary>>, %{state: :sb} = d, acc),
    do: step(rest, %{d | state: :sb_iac}, acc)

  defp step(<<b, rest::binary>>, %{state: :sb} = d, acc), do: sb_byte(rest, d, b, acc)

  # IAC IAC inside a subnegotiation is one 255; IAC SE ends it
  defp step(<<@iac, rest::binary>>, %{state: :sb_iac} = d, acc),
    do: sb_byte(rest, %{d | state: :sb}, @iac, acc)

  defp step(<<@se, rest::binary>>, %{state: :sb_iac} = d, acc) do
    event =
      if d.sb_size > @max_subneg,
        do: {:error, :subneg_too_long},
        else: subneg_event(IO.iodata_to_binary(d.sb))

    step(rest, %{d | state: :data, sb: [], sb_size: 0}, [event | acc])
  end

  # IAC and anything else inside a subnegotiation: a broken one; take it as ended
  defp step(<<_b, rest::binary>>, %{state: :sb_iac} = d, acc),
    do: step(rest, %{d | state: :data, sb: [], sb_size: 0}, [{:error, :bad_subneg} | acc])

  defp sb_byte(rest, d, b, acc) do
    d =
      if d.sb_size >= @max_subneg,
        do: %{d | sb_size: d.sb_size + 1},
        else: %{d | sb: [d.sb | [b]], sb_size: d.sb_size + 1}

    step(rest, d, acc)
  end

  defp verb_atom(@will), do: :will
  defp verb_atom(@wont), do: :wont
  defp verb_atom(@t_do), do: :do
  defp verb_atom(@t_dont), do: :dont

  defp subneg_event(<<@com_port, command, payload::binary>>),
    do: {:com_port, com_port_reply(command, payload)}

  defp subneg_event(<<opt, payload::binary>>), do: {:subneg, opt, payload}
  defp subneg_event(<<>>), do: {:error, :bad_subneg}

  defp com_port_reply(101, <<baud::32>>), do: {:baud, baud}
  defp com_port_reply(102, <<n>>), do: {:data_size, n}
  defp com_port_reply(103, <<p>>) when p <= 5, do: {:parity, key_of(@parities, p)}
  defp com_port_reply(104, <<s>>) when s <= 3, do: {:stop_size, stop_of(s)}
  defp com_port_reply(105, <<c>>), do: {:control, control_of(c)}
  defp com_port_reply(106, <<m>>), do: {:linestate, m}
  defp com_port_reply(107, <<m>>), do: {:modemstate, m}
  defp com_port_reply(110, <<m>>), do: {:linestate_mask, m}
  defp com_port_reply(111, <<m>>), do: {:modemstate_mask, m}
  defp com_port_reply(command, payload), do: {:unknown, command, payload}

  defp key_of(list, value), do: list |> Enum.find(fn {_, v} -> v == value end) |> elem(0)

  defp stop_of(1), do: 1
  defp stop_of(2), do: 2
  defp stop_of(3), do: :one_and_half
  defp stop_of(0), do: :ask

  # SET-CONTROL's answer may be about inbound flow control or break and DTR/RTS too (4–19)
  defp control_of(c) when c in 0..3, do: key_of(@controls, c)
  defp control_of(c), do: :"other_#{c}"
end
