defmodule Vws.Links.DDCMP.Frame do
  @moduledoc """
  DDCMP V4.1 message codec: the bottom layer of the VAL II supervisory link (PROTOCOLS.md §3,
  seed §4.3.2–4.3.4). Pure: no processes, no I/O.

  Three message classes, each starting with an 8-byte header (6 bytes and their CRC-16/ARC,
  low byte first, see `Vws.Codecs.CRC16`):

    * data, SOH 0x81: COUNT (14 bits, low byte then high 6 bits with QSYNC 0x40 and SELECT 0x80),
      RESP, NUM, ADDR, header CRC, then COUNT data bytes and their CRC — `Vws.Links.DDCMP.Frame.Data`;
    * control, ENQ 0x05: TYPE, SUBTYPE (6 bits) with the same two flags, RCVR, SNDR, ADDR, CRC —
      `Vws.Links.DDCMP.Frame.Control` (ACK 1, NAK 2, REP 3, STRT 6, STACK 7);
    * maintenance, DLE 0x90: laid out as a data message whose RESP/NUM bytes are zero fill —
      `Vws.Links.DDCMP.Frame.Maintenance`. We never use it; the link halts on receiving one.

  `encode/2` appends one DEL (0xFF) fill byte after every message, as we always send one.

      iex> Vws.Links.DDCMP.Frame.strt() |> Vws.Links.DDCMP.Frame.encode() |> IO.iodata_to_binary()
      <<0x05, 0x06, 0xC0, 0x00, 0x00, 0x01, 0x75, 0x95, 0xFF>>
      iex> {frames, _decoder} =
      ...>   Vws.Links.DDCMP.Frame.feed(Vws.Links.DDCMP.Frame.new(), <<0x96, 0x96, 5, 6, 0xC0, 0, 0, 1, 0x75, 0x95>>)
      iex> frames
      [%Vws.Links.DDCMP.Frame.Control{type: :strt, subtype: 0, rcvr: 0, sndr: 0, addr: 1, qsync: true, select: true}]

  ## Receiving

  `new/1` makes an incremental decoder and `feed/2` gives it bytes as they arrive. It skips SYN
  (0x96), DEL (0xFF) and any other byte that is not a class byte between messages. On a class
  byte it accepts the header only if the header CRC checks; otherwise it drops that one byte and
  rescans, so a message beginning inside a rejected candidate is still found. QSYNC and SELECT
  are decoded into the structs but mean nothing to the receiver.

  Problems come out in order among the frames as `{:error, %Vws.Links.DDCMP.Error{}}`:

    * `:header_crc` once per resynchronisation episode — from the first rejected header until a
      header is next accepted — so line noise cannot grow the result list byte by byte. The link
      learns that a header was lost; whether to NAK (reason 1) is its decision.
    * `:data_crc` with the good header's `num`, `resp` and `count`, so the link can NAK reason 2
      and still take the piggy-backed RESP.
    * `:too_long` when COUNT exceeds `:max_data`; the COUNT data bytes and their CRC are then
      skipped as they arrive, never buffered.
    * `:header_format` for a good header that is no valid message (unknown control TYPE,
      maintenance fill bytes not zero); the 8 header bytes are dropped.

  The decoder never holds more than one maximal message (`8 + max_data + 2` bytes) between
  calls. A data message with COUNT 0 is accepted and returned as-is (decision: the codec
  reports, the link judges).
  """

  import Bitwise

  alias Vws.Codecs.CRC16
  alias Vws.Links.DDCMP.Error

  @soh 0x81
  @enq 0x05
  @dle 0x90
  @del 0xFF

  @qsync 0x40
  @select 0x80

  @max_count 0x3FFF
  @default_max_data 4096

  @header_size 8
  @crc_size 2

  @control_types %{ack: 1, nak: 2, rep: 3, strt: 6, stack: 7}
  @control_type_names Map.new(@control_types, fn {name, code} -> {code, name} end)

  @nak_reasons %{
    header_crc: 1,
    data_crc: 2,
    rep_response: 3,
    no_buffer: 8,
    overrun: 9,
    too_long: 16,
    header_format: 17
  }
  @nak_reason_names Map.new(@nak_reasons, fn {name, code} -> {code, name} end)

  defmodule Data do
    @moduledoc """
    A numbered DDCMP data message (class SOH 0x81): `num` is this message's number, `resp` the
    number of the last message correctly received from the peer, both mod 256.
    """
    defstruct resp: 0, num: 0, addr: 1, qsync: false, select: false, data: <<>>

    @type t :: %__MODULE__{
            resp: 0..255,
            num: 0..255,
            addr: 0..255,
            qsync: boolean,
            select: boolean,
            data: binary
          }
  end

  defmodule Control do
    @moduledoc """
    An unnumbered DDCMP control message (class ENQ 0x05). `subtype` is the NAK reason code for a
    NAK (see `Vws.Links.DDCMP.Frame.nak_reason/1`) and 0 otherwise; `rcvr` carries RESP in ACK and NAK,
    `sndr` carries NUM in REP.
    """
    defstruct type: :ack, subtype: 0, rcvr: 0, sndr: 0, addr: 1, qsync: false, select: false

    @type t :: %__MODULE__{
            type: :ack | :nak | :rep | :strt | :stack,
            subtype: 0..63,
            rcvr: 0..255,
            sndr: 0..255,
            addr: 0..255,
            qsync: boolean,
            select: boolean
          }
  end

  defmodule Maintenance do
    @moduledoc """
    A DDCMP maintenance message (class DLE 0x90). Not used on the VAL II link: receiving one
    halts it. Both flags are set in maintenance messages, hence the defaults.
    """
    defstruct addr: 1, qsync: true, select: true, data: <<>>

    @type t :: %__MODULE__{addr: 0..255, qsync: boolean, select: boolean, data: binary}
  end

  defmodule Decoder do
    @moduledoc false
    defstruct buffer: <<>>, max_data: 4096, skip: 0, resyncing: false
  end

  @type t :: Data.t() | Control.t() | Maintenance.t()
  @type nak_reason ::
          :header_crc
          | :data_crc
          | :rep_response
          | :no_buffer
          | :overrun
          | :too_long
          | :header_format
  @opaque decoder :: %Decoder{}

  defguardp is_byte(value) when is_integer(value) and value in 0..255

  # Constructors -------------------------------------------------------------------------------

  @doc "ACK: every data message up to `resp` was received correctly."
  @spec ack(0..255) :: Control.t()
  def ack(resp) when is_byte(resp), do: %Control{type: :ack, rcvr: resp}

  @doc """
  NAK: a message was refused for `reason` (an atom of `t:nak_reason/0` or a 6-bit code);
  `resp` is the last message received correctly.

      iex> Vws.Links.DDCMP.Frame.nak(:rep_response, 1)
      %Vws.Links.DDCMP.Frame.Control{type: :nak, subtype: 3, rcvr: 1}
  """
  @spec nak(nak_reason | 0..63, 0..255) :: Control.t()
  def nak(reason, resp) when is_byte(resp) do
    %Control{type: :nak, subtype: nak_code(reason), rcvr: resp}
  end

  @doc "REP: asks the peer to report whether it holds every message up to `num`."
  @spec rep(0..255) :: Control.t()
  def rep(num) when is_byte(num), do: %Control{type: :rep, sndr: num}

  @doc "STRT: start or restart the link (both flags set, as on the wire)."
  @spec strt() :: Control.t()
  def strt, do: %Control{type: :strt, qsync: true, select: true}

  @doc "STACK: answer to STRT (both flags set, as on the wire)."
  @spec stack() :: Control.t()
  def stack, do: %Control{type: :stack, qsync: true, select: true}

  @doc "A data message numbered `num`, acknowledging up to `resp`, carrying `bytes`."
  @spec data(0..255, 0..255, iodata) :: Data.t()
  def data(num, resp, bytes) when is_byte(num) and is_byte(resp) do
    %Data{num: num, resp: resp, data: IO.iodata_to_binary(bytes)}
  end

  @doc """
  The NAK reason name for a code, or the code itself if DDCMP does not name it.

      iex> Vws.Links.DDCMP.Frame.nak_reason(2)
      :data_crc
      iex> Vws.Links.DDCMP.Frame.nak_reason(5)
      5
  """
  @spec nak_reason(0..63) :: nak_reason | 0..63
  def nak_reason(code) when is_integer(code) and code in 0..63,
    do: Map.get(@nak_reason_names, code, code)

  @doc """
  The NAK reason code for a name (a code in 0..63 is returned unchanged).

      iex> Vws.Links.DDCMP.Frame.nak_code(:too_long)
      16
  """
  @spec nak_code(nak_reason | 0..63) :: 0..63
  def nak_code(code) when is_integer(code) and code in 0..63, do: code

  def nak_code(name) when is_map_key(@nak_reasons, name), do: Map.fetch!(@nak_reasons, name)

  def nak_code(other), do: raise(ArgumentError, "not a DDCMP NAK reason: #{inspect(other)}")

  # Encoding -----------------------------------------------------------------------------------

  @doc """
  The bytes of `frame` on the wire, followed by one DEL fill byte unless `fill: false`.

  Raises `ArgumentError` for a frame that cannot be sent: data longer than 16383 bytes, or a
  field out of range.
  """
  @spec encode(t, keyword) :: iodata
  def encode(frame, opts \\ []) do
    message = encode_message(frame)
    if Keyword.get(opts, :fill, true), do: [message, @del], else: message
  end

  defp encode_message(%Control{type: type, subtype: subtype} = c)
       when is_map_key(@control_types, type) and is_integer(subtype) and subtype in 0..63 and
              is_byte(c.rcvr) and is_byte(c.sndr) and is_byte(c.addr) do
    header =
      <<@enq, Map.fetch!(@control_types, type), flags(c) ||| subtype, c.rcvr, c.sndr, c.addr>>

    [header, CRC16.encode(CRC16.compute(header))]
  end

  defp encode_message(%Data{data: data} = d)
       when is_binary(data) and byte_size(data) <= @max_count and is_byte(d.resp) and
              is_byte(d.num) and is_byte(d.addr) do
    counted(@soh, flags(d), d.resp, d.num, d.addr, data)
  end

  defp encode_message(%Maintenance{data: data} = m)
       when is_binary(data) and byte_size(data) <= @max_count and is_byte(m.addr) do
    counted(@dle, flags(m), 0, 0, m.addr, data)
  end

  defp encode_message(frame) do
    raise ArgumentError, "cannot encode DDCMP message #{inspect(frame, limit: 8)}"
  end

  defp counted(class, flags, resp, num, addr, data) do
    count = byte_size(data)
    header = <<class, band(count, 0xFF), flags ||| count >>> 8, resp, num, addr>>

    [
      header,
      CRC16.encode(CRC16.compute(header)),
      data,
      CRC16.encode(CRC16.compute(data))
    ]
  end

  defp flags(%{qsync: qsync, select: select}) do
    if(qsync, do: @qsync, else: 0) ||| if select, do: @select, else: 0
  end

  # Decoding -----------------------------------------------------------------------------------

  @doc """
  A new incremental decoder.

  Options: `max_data` — the largest data COUNT accepted (default #{@default_max_data}, at most
  #{@max_count}); longer messages are reported as `:too_long` and skipped. The default leaves
  room for the largest VAL message (3 + 256 bytes) many times over while bounding the buffer.
  """
  @spec new(keyword) :: decoder
  def new(opts \\ []) do
    max_data = Keyword.get(opts, :max_data, @default_max_data)

    unless is_integer(max_data) and max_data in 0..@max_count do
      raise ArgumentError, "max_data must be in 0..#{@max_count}, got: #{inspect(max_data)}"
    end

    %Decoder{max_data: max_data}
  end

  @doc """
  Gives the decoder the next received bytes; returns the messages and errors they complete, in
  order, and the decoder to use next.
  """
  @spec feed(decoder, iodata) :: {[t | {:error, Error.t()}], decoder}
  def feed(%Decoder{buffer: buffer} = decoder, bytes) do
    scan(buffer <> IO.iodata_to_binary(bytes), %Decoder{decoder | buffer: <<>>}, [])
  end

  @doc "How many received bytes the decoder holds while waiting for the rest of a message."
  @spec buffered_bytes(decoder) :: non_neg_integer
  def buffered_bytes(%Decoder{buffer: buffer}), do: byte_size(buffer)

  # Skipping the body of a too-long message: drop bytes as they come, keep none.
  defp scan(bytes, %Decoder{skip: skip} = decoder, acc) when skip > 0 do
    case bytes do
      <<_::binary-size(skip), rest::binary>> -> scan(rest, %Decoder{decoder | skip: 0}, acc)
      _ -> done(%Decoder{decoder | skip: skip - byte_size(bytes)}, <<>>, acc)
    end
  end

  defp scan(bytes, decoder, acc) do
    case :binary.match(bytes, [<<@soh>>, <<@enq>>, <<@dle>>]) do
      :nomatch ->
        done(decoder, <<>>, acc)

      {at, 1} ->
        <<_fill::binary-size(at), candidate::binary>> = bytes
        candidate(candidate, decoder, acc)
    end
  end

  defp candidate(
         <<header::binary-size(@header_size - @crc_size), check::binary-size(@crc_size),
           rest::binary>> = bytes,
         decoder,
         acc
       ) do
    if CRC16.compute([header, check]) == 0 do
      message(header, rest, bytes, %Decoder{decoder | resyncing: false}, acc)
    else
      <<_class, next::binary>> = bytes
      acc = if decoder.resyncing, do: acc, else: [{:error, %Error{reason: :header_crc}} | acc]
      scan(next, %Decoder{decoder | resyncing: true}, acc)
    end
  end

  defp candidate(partial_header, decoder, acc), do: done(decoder, partial_header, acc)

  defp message(
         <<@enq, type, flags_subtype, rcvr, sndr, addr>> = header,
         rest,
         _bytes,
         decoder,
         acc
       ) do
    item =
      case Map.fetch(@control_type_names, type) do
        {:ok, name} ->
          %Control{
            type: name,
            subtype: band(flags_subtype, 0x3F),
            rcvr: rcvr,
            sndr: sndr,
            addr: addr,
            qsync: band(flags_subtype, @qsync) != 0,
            select: band(flags_subtype, @select) != 0
          }

        :error ->
          {:error, %Error{reason: :header_format, header: :binary.copy(header)}}
      end

    scan(rest, decoder, [item | acc])
  end

  defp message(<<@dle, _, _, fill1, fill2, _>> = header, rest, _bytes, decoder, acc)
       when fill1 != 0 or fill2 != 0 do
    error = %Error{reason: :header_format, header: :binary.copy(header)}
    scan(rest, decoder, [{:error, error} | acc])
  end

  defp message(<<class, count_low, flags_count, resp, num, addr>>, rest, bytes, decoder, acc) do
    count = (band(flags_count, 0x3F) <<< 8) + count_low
    {resp, num} = if class == @soh, do: {resp, num}, else: {nil, nil}

    case rest do
      _ when count > decoder.max_data ->
        error = %Error{
          reason: :too_long,
          num: num,
          resp: resp,
          count: count,
          max: decoder.max_data
        }

        scan(rest, %Decoder{decoder | skip: count + @crc_size}, [{:error, error} | acc])

      <<data::binary-size(count), check::binary-size(@crc_size), rest::binary>> ->
        item =
          cond do
            CRC16.compute([data, check]) != 0 ->
              {:error, %Error{reason: :data_crc, num: num, resp: resp, count: count}}

            class == @soh ->
              %Data{
                resp: resp,
                num: num,
                addr: addr,
                qsync: band(flags_count, @qsync) != 0,
                select: band(flags_count, @select) != 0,
                data: :binary.copy(data)
              }

            true ->
              %Maintenance{
                addr: addr,
                qsync: band(flags_count, @qsync) != 0,
                select: band(flags_count, @select) != 0,
                data: :binary.copy(data)
              }
          end

        scan(rest, decoder, [item | acc])

      _incomplete ->
        done(decoder, bytes, acc)
    end
  end

  # Copy what we keep so a large fed binary is not held alive by a small remainder.
  defp done(decoder, keep, acc) do
    {Enum.reverse(acc), %Decoder{decoder | buffer: :binary.copy(keep)}}
  end
end
