defmodule Vws.Links.DNC.Frame do
  @moduledoc """
  Pure codec of the GE-2000 DNC Level 2 link, the ANSI X3.28-style half-duplex line between MONARCH
  and the VMC (PROTOCOLS.md §2, seed §3.2–3.2.7).

  On the line there are three kinds of thing, all decoded to plain terms:

    * control sequences — `:enq` (ENQ), `:ack0` (DLE `0`), `:ack1` (DLE `1`), `:wack` (DLE `;`),
      `:nak` (NAK), `:eot` (EOT);
    * command blocks — `Vws.Links.DNC.Frame.Command`, `SOH c1 c2 c3 STX text ETX BCC`;
    * text blocks — `Vws.Links.DNC.Frame.Text`, `STX text ETX BCC`.

      iex> cmd = %Vws.Links.DNC.Frame.Command{direction: :receive, check: :lrc, operation: :table, text: "TOFFSET"}
      iex> Vws.Links.DNC.Frame.encode(cmd) |> IO.iodata_to_binary()
      <<0x01, "RNO", 0x02, "TOFFSET", 0x03, 0x0B>>
      iex> {frames, _decoder} = Vws.Links.DNC.Frame.feed(Vws.Links.DNC.Frame.new(), <<0x05, 0x7F, 0x10, ?0>>)
      iex> frames
      [:enq, :ack0]

  ## Decisions (where PROTOCOLS.md §2 and the seed are silent)

    * **BCC coverage.** LRC is the XOR of every byte after SOH through ETX for a command block (so
      it covers the three header characters and STX), and after STX through ETX for a text block,
      the X3.28 practice: the character that opens the block is never counted. CRC is CRC-16/ARC
      (`Vws.Codecs.CRC16`) over the same bytes, sent low byte first.
    * **Check mode of text blocks.** A text block does not say how it is checked; the preceding
      command chose. The decoder therefore carries a mode (`:lrc` at start, `new(check: ...)`,
      `set_check/2`). A valid command block it decodes switches the mode to the command's own `N`/`C`.
      EOT resets the mode to `:lrc` — except the first EOT after an `R` command, which hands the
      line over to the slave: its text blocks follow under the same mode, and the EOT that ends them
      resets it. The decoder only sees what the peer sends, so the side that *sent* the command
      (the CEC for `RCS`, say) must call `set_check/2` itself.
    * **DEL** (0x7F) is padding: the GE-2000 sends `ENQ DEL` and `EOT DEL`. It is skipped between
      blocks and between DLE and its second character, so `ENQ DEL` decodes as `:enq`. Inside a block
      every byte counts: DEL in text is data (covered by the BCC), DEL in a header is malformed.
      `encode(control_or_frame, pad: true)` appends one DEL, to speak like the GE-2000.
    * **No transparency.** The link runs X3.28 non-transparent: text may hold any byte except the
      transmission controls SOH STX ETX EOT ENQ ACK DLE NAK SYN ETB. `encode/2` raises
      `ArgumentError` on them. Part programs are ASCII lines ended by LF, which is fine;
      `split_text/2` cuts a program into block texts.
    * **A damaged block is one error.** A transmission control other than ETX inside a received
      block breaks it off: the block is reported `:malformed` once — the receiver answers it like
      a bad BCC, with one NAK — and the rest of it, through its ETX and BCC, is dropped with it,
      so a bit error that turns a `0` into DLE or an LF into STX can neither draw a second
      reply nor start a "block" from the tail. The drop ends early at what a sender sends next
      (SOH, STX, EOT, ENQ), which is decoded. Two controls are special: EOT is the sender giving
      the transmission up (X3.28 abort) and is decoded after the error; ENQ is X3.28's block
      abort ("discard this block"), whose answer is the NAK the error draws, so it is part of the
      break and not decoded on its own. A SOH followed by anything but a valid header is
      `:malformed` the same way, and the header's own STX, further on, is part of the dropped
      block, not a new one.
    * **Block size.** At most `max_text` (default 256) text bytes per block, command or text.
      Longer blocks are refused by `encode/2` and reported `:too_long` by the decoder.
    * **SOH runs.** The seed shows the CEC sending `SOH SOH SOH` after an upload; a SOH immediately
      followed by another SOH is dropped silently as fill. A SOH followed by anything but a valid
      header is `:malformed`.
    * **Garbage** between blocks yields one `:unexpected_byte` error per run, never one per byte.
      An ETX in it ends a block whose STX or SOH was damaged: the BCC after it is skipped, never
      decoded, so a BCC that happens to be EOT cannot end the transmission.
      The decoder keeps at most one unfinished block (`max_text + 8` bytes), copied out of the
      input, and the text of a decoded block is a copy too: a block never keeps the whole chunk
      it arrived in alive.
  """

  import Bitwise

  alias Vws.Codecs.CRC16
  alias Vws.Links.DNC.Error

  @soh 0x01
  @stx 0x02
  @etx 0x03
  @eot 0x04
  @enq 0x05
  @ack 0x06
  @dle 0x10
  @nak 0x15
  @syn 0x16
  @etb 0x17
  @del 0x7F
  @ack0 ?0
  @ack1 ?1
  @wack ?;

  # X3.28 transmission controls: never in non-transparent text.
  @transmission_controls [@soh, @stx, @etx, @eot, @enq, @ack, @dle, @nak, @syn, @etb]
  @control_patterns Enum.map(@transmission_controls, &<<&1>>)
  # What a sender sends after a block: they end the skip of a dropped block.
  @resync [@soh, @stx, @eot, @enq]

  @default_max_text 256

  @directions %{send: ?S, receive: ?R}
  @checks %{lrc: ?N, crc: ?C}
  @operations %{
    part_program: ?S,
    table: ?O,
    remote_control: ?K,
    status: ?L,
    delete: ?D,
    directory: ?F,
    download_execute: ?E,
    binary: ?Q
  }
  @direction_of Map.new(@directions, fn {k, v} -> {v, k} end)
  @check_of Map.new(@checks, fn {k, v} -> {v, k} end)
  @operation_of Map.new(@operations, fn {k, v} -> {v, k} end)
  @header_chars [Map.keys(@direction_of), Map.keys(@check_of), Map.keys(@operation_of), [@stx]]

  defmodule Command do
    @moduledoc """
    A command block, `SOH c1 c2 c3 STX text ETX BCC` (seed §3.2.1).

    `direction` is c1 (`:send` = `S`, the slave accepts text; `:receive` = `R`, the slave becomes
    master after EOT); `check` is c2 (`:lrc` = `N`, `:crc` = `C`), which checks this block and the
    text blocks after it; `operation` is c3: `:part_program` `S`, `:table` `O`,
    `:remote_control` `K`, `:status` `L`, `:delete` `D`, `:directory` `F`,
    `:download_execute` `E`, `:binary` `Q`. `text` is a file name, file number or table name, often
    empty.
    """

    @type operation ::
            :part_program
            | :table
            | :remote_control
            | :status
            | :delete
            | :directory
            | :download_execute
            | :binary
    @type t :: %__MODULE__{
            direction: :send | :receive,
            check: Vws.Links.DNC.Frame.check(),
            operation: operation,
            text: binary
          }
    defstruct direction: :send, check: :lrc, operation: :part_program, text: ""
  end

  defmodule Text do
    @moduledoc """
    A text block, `STX text ETX BCC`, checked as the preceding command chose (seed §3.2.1).
    """
    @type t :: %__MODULE__{text: binary}
    defstruct text: ""
  end

  defmodule Decoder do
    @moduledoc false
    # state: :idle between blocks; :garbage inside a reported run of unexpected bytes;
    # {:skip, check} discarding an overlong or damaged block; {:skip_header, left, check} the
    # `left` header positions after a damaged header byte; {:skip_bcc, n} discarding the last n
    # BCC bytes.
    # reverse?: an R command was decoded and its line-turnaround EOT not yet seen.
    @type t :: %__MODULE__{
            check: Vws.Links.DNC.Frame.check(),
            max_text: pos_integer,
            reverse?: boolean,
            state:
              :idle
              | :garbage
              | {:skip, Vws.Links.DNC.Frame.check()}
              | {:skip_header, 1..3, Vws.Links.DNC.Frame.check()}
              | {:skip_bcc, 1..2},
            buffer: binary
          }
    defstruct check: :lrc, max_text: 256, reverse?: false, state: :idle, buffer: <<>>
  end

  @type check :: :lrc | :crc
  @type control :: :enq | :ack0 | :ack1 | :wack | :nak | :eot
  @type frame :: Command.t() | Text.t()
  @type decoder :: Decoder.t()

  ## Encoding

  @doc """
  Encodes a control sequence, command block or text block as iodata.

  Options: `check: :lrc | :crc` (text blocks only, default `:lrc`: a command carries its own),
  `pad: true` to append one DEL as the GE-2000 does, `max_text` (default #{@default_max_text}).
  Raises `ArgumentError` on text with a transmission control character or over `max_text` bytes.

      iex> Vws.Links.DNC.Frame.encode(:ack1) |> IO.iodata_to_binary()
      <<0x10, ?1>>
      iex> Vws.Links.DNC.Frame.encode(:enq, pad: true) |> IO.iodata_to_binary()
      <<0x05, 0x7F>>
      iex> Vws.Links.DNC.Frame.encode(%Vws.Links.DNC.Frame.Text{text: ""}, check: :crc) |> IO.iodata_to_binary()
      <<0x02, 0x03, 0x40, 0x01>>
  """
  @spec encode(frame | control, keyword) :: iodata
  def encode(frame_or_control, opts \\ []) do
    opts = Keyword.validate!(opts, check: :lrc, pad: false, max_text: @default_max_text)
    pad = if opts[:pad], do: [@del], else: []
    [do_encode(frame_or_control, opts) | pad]
  end

  defp do_encode(:enq, _opts), do: [@enq]
  defp do_encode(:ack0, _opts), do: [@dle, @ack0]
  defp do_encode(:ack1, _opts), do: [@dle, @ack1]
  defp do_encode(:wack, _opts), do: [@dle, @wack]
  defp do_encode(:nak, _opts), do: [@nak]
  defp do_encode(:eot, _opts), do: [@eot]

  defp do_encode(%Command{} = command, opts) do
    header = [
      char!(@directions, command.direction, :direction),
      char!(@checks, command.check, :check),
      char!(@operations, command.operation, :operation)
    ]

    covered = [header, @stx, text!(command.text, opts[:max_text]), @etx]
    [@soh, covered, bcc(covered, command.check)]
  end

  defp do_encode(%Text{text: text}, opts) do
    check = opts[:check]
    _ = char!(@checks, check, :check)
    covered = [text!(text, opts[:max_text]), @etx]
    [@stx, covered, bcc(covered, check)]
  end

  defp do_encode(other, _opts) do
    raise ArgumentError, "not a DNC control or block: #{inspect(other)}"
  end

  defp char!(table, key, field) do
    case table do
      %{^key => char} ->
        char

      _ ->
        raise ArgumentError,
              "invalid #{field} #{inspect(key)}, expected one of #{inspect(Map.keys(table))}"
    end
  end

  defp text!(text, max) when is_binary(text) do
    if byte_size(text) > max do
      raise ArgumentError, "block text is #{byte_size(text)} bytes, over the maximum of #{max}"
    end

    case :binary.match(text, @control_patterns) do
      :nomatch ->
        text

      {pos, 1} ->
        raise ArgumentError,
              "block text holds transmission control 0x#{Base.encode16(binary_part(text, pos, 1))} " <>
                "at byte #{pos}: the link is non-transparent"
    end
  end

  defp text!(text, _max),
    do: raise(ArgumentError, "block text must be a binary, got #{inspect(text)}")

  @doc """
  The block check of `covered` (the bytes after SOH or STX through ETX) as sent on the line: one LRC
  byte, or the CRC-16/ARC low byte first.

      iex> Vws.Links.DNC.Frame.bcc(["SNS", 0x02, 0x03], :lrc)
      <<0x4F>>
  """
  @spec bcc(iodata, check) :: binary
  def bcc(covered, :lrc), do: <<lrc(IO.iodata_to_binary(covered))>>
  def bcc(covered, :crc), do: CRC16.encode(CRC16.compute(covered))

  defp lrc(bin), do: for(<<byte <- bin>>, reduce: 0, do: (acc -> bxor(acc, byte)))

  @doc """
  Cuts `program` into block texts of at most `max` bytes (default #{@default_max_text}), ending each
  at the last LF that fits; a line longer than `max` is cut at `max`. Concatenating the result gives
  `program` back; an empty program gives `[]`.

  Two blocks in a row are never equal (for `max` of 2 or more): a block equal to the one before
  is cut shorter (at an earlier LF, else a byte shorter; a one-byte block a byte longer). Blocks
  carry no number, so a receiver takes a block equal to the last one it accepted for a copy of
  it, always — a copy taken as a new block would make a drip-fed machine run it twice
  (PROTOCOLS.md §2 "Acknowledgement"; docs/dnc-drip-feed.md "Copies").

      iex> Vws.Links.DNC.Frame.split_text("N10 G00\\nN20 M30\\n", 12)
      ["N10 G00\\n", "N20 M30\\n"]

      iex> Vws.Links.DNC.Frame.split_text("G04\\nG04\\nG04\\n", 4)
      ["G04\\n", "G04", "\\n", "G04\\n"]
  """
  @spec split_text(binary, pos_integer) :: [binary]
  def split_text(program, max \\ @default_max_text)
      when is_binary(program) and is_integer(max) and max > 0 do
    do_split(program, max, [])
  end

  defp do_split(<<>>, max, acc), do: finish(acc, max)

  defp do_split(rest, max, acc) do
    size = greedy_cut(rest, max)

    size =
      case acc do
        [previous | _] when previous == binary_part(rest, 0, size) ->
          other_cut(rest, size, max)

        _ ->
          size
      end

    <<part::binary-size(size), rest::binary>> = rest
    do_split(rest, max, [part | acc])
  end

  defp greedy_cut(rest, max) when byte_size(rest) <= max, do: byte_size(rest)

  defp greedy_cut(rest, max) do
    case :binary.matches(binary_part(rest, 0, max), "\n") do
      [] -> max
      matches -> (matches |> List.last() |> elem(0)) + 1
    end
  end

  # The block would equal the one before: the greedy cut of one byte less (at the last LF
  # before its end, else a byte shorter) differs by its length; a one-byte block takes one more
  # byte if there is one.
  defp other_cut(rest, size, _max) when size > 1, do: greedy_cut(rest, size - 1)

  defp other_cut(rest, 1, max) when max >= 2 and byte_size(rest) >= 2, do: 2
  defp other_cut(_rest, size, _max), do: size

  # The last block can be left equal to the one before (a one-byte end after a one-byte block):
  # the last few blocks are cut again, searching (within a budget) for cuts whose neighbours
  # differ. What cannot be (a `max` of 1) stays, and DNC.Session refuses to send it.
  defp finish([same, same | _] = acc, max) when max >= 2, do: repair(acc, max, 2)
  defp finish(acc, _max), do: Enum.reverse(acc)

  defp repair(acc, max, k) when k <= 8 and length(acc) >= k do
    {suffix, fixed} = Enum.split(acc, k)
    suffix = suffix |> Enum.reverse() |> IO.iodata_to_binary()

    case cuts(suffix, max, List.first(fixed), 10_000) do
      {:ok, parts, _budget} -> Enum.reverse(fixed, parts)
      {:error, _budget} -> repair(acc, max, k + 1)
    end
  end

  defp repair(acc, _max, _k), do: Enum.reverse(acc)

  defp cuts(<<>>, _max, _previous, budget), do: {:ok, [], budget}
  defp cuts(_rest, _max, _previous, budget) when budget <= 0, do: {:error, 0}

  defp cuts(rest, max, previous, budget) do
    sizes = Enum.uniq([greedy_cut(rest, max) | Enum.to_list(min(max, byte_size(rest))..1)])

    Enum.reduce_while(sizes, {:error, budget - 1}, fn size, {:error, budget} ->
      <<part::binary-size(size), after_part::binary>> = rest

      case if(part == previous, do: {:error, budget}, else: cuts(after_part, max, part, budget)) do
        {:ok, parts, budget} -> {:halt, {:ok, [part | parts], budget}}
        {:error, budget} -> {:cont, {:error, budget}}
      end
    end)
  end

  ## Decoding

  @doc """
  A new decoder. Options: `check` (mode for text blocks until a command sets it, default `:lrc`),
  `max_text` (default #{@default_max_text}).
  """
  @spec new(keyword) :: decoder
  def new(opts \\ []) do
    opts = Keyword.validate!(opts, check: :lrc, max_text: @default_max_text)
    check = check!(opts[:check])
    max = opts[:max_text]

    unless is_integer(max) and max > 0 do
      raise ArgumentError, "max_text must be a positive integer, got #{inspect(max)}"
    end

    %Decoder{check: check, max_text: max}
  end

  @doc """
  Sets the check mode for the text blocks that follow, as chosen by a command this side sent.
  """
  @spec set_check(decoder, check) :: decoder
  def set_check(%Decoder{} = decoder, check), do: %{decoder | check: check!(check)}

  @doc "The check mode the decoder will apply to the next text block."
  @spec check(decoder) :: check
  def check(%Decoder{check: check}), do: check

  defp check!(check) when check in [:lrc, :crc], do: check

  defp check!(check),
    do: raise(ArgumentError, "check must be :lrc or :crc, got #{inspect(check)}")

  @doc """
  Feeds received bytes; returns the controls, blocks and errors completed by them, in line order.

      iex> bytes = <<0x01, "SNS", 0x02, 0x03, 0x4F, 0x02, "N10 M30\\n", 0x03, 0x28, 0x04, 0x7F>>
      iex> {frames, _decoder} = Vws.Links.DNC.Frame.feed(Vws.Links.DNC.Frame.new(), bytes)
      iex> frames
      [%Vws.Links.DNC.Frame.Command{direction: :send, check: :lrc, operation: :part_program, text: ""},
       %Vws.Links.DNC.Frame.Text{text: "N10 M30\\n"}, :eot]
  """
  @spec feed(decoder, binary) :: {[frame | control | {:error, Error.t()}], decoder}
  def feed(%Decoder{buffer: buffer} = decoder, bytes) when is_binary(bytes) do
    {acc, decoder} = parse(buffer <> bytes, %{decoder | buffer: <<>>}, [])
    {Enum.reverse(acc), decoder}
  end

  # Resync after an overlong or damaged block: to its ETX (then its BCC) or to what a sender
  # sends next.
  defp parse(<<>>, decoder, acc), do: {acc, decoder}

  defp parse(<<byte, rest::binary>> = bytes, %{state: {:skip, check}} = decoder, acc) do
    cond do
      byte == @etx -> parse(rest, %{decoder | state: {:skip_bcc, bcc_size(check)}}, acc)
      byte in @resync -> parse(bytes, %{decoder | state: :idle}, acc)
      true -> parse(rest, decoder, acc)
    end
  end

  # The rest of a damaged header: up to and including its STX, unless something new starts.
  defp parse(<<byte, rest::binary>> = bytes, %{state: {:skip_header, left, check}} = decoder, acc) do
    cond do
      byte == @stx -> parse(rest, %{decoder | state: {:skip, check}}, acc)
      byte in @resync -> parse(bytes, idle(decoder), acc)
      left == 1 -> parse(rest, %{decoder | state: {:skip, check}}, acc)
      true -> parse(rest, %{decoder | state: {:skip_header, left - 1, check}}, acc)
    end
  end

  defp parse(<<_, rest::binary>>, %{state: {:skip_bcc, n}} = decoder, acc) do
    state = if n == 1, do: :idle, else: {:skip_bcc, n - 1}
    parse(rest, %{decoder | state: state}, acc)
  end

  defp parse(<<@del, rest::binary>>, decoder, acc), do: parse(rest, decoder, acc)
  defp parse(<<@enq, rest::binary>>, decoder, acc), do: parse(rest, idle(decoder), [:enq | acc])
  defp parse(<<@nak, rest::binary>>, decoder, acc), do: parse(rest, idle(decoder), [:nak | acc])

  defp parse(<<@eot, rest::binary>>, decoder, acc),
    do: parse(rest, after_eot(decoder), [:eot | acc])

  defp parse(<<@dle, rest::binary>>, decoder, acc), do: parse_dle(rest, decoder, acc)

  # SOH SOH: the first is fill (the seed's CEC sends SOH SOH SOH).
  defp parse(<<@soh, @soh, rest::binary>>, decoder, acc),
    do: parse(<<@soh, rest::binary>>, decoder, acc)

  defp parse(<<@soh, rest::binary>> = bytes, decoder, acc),
    do: parse_header(rest, bytes, decoder, acc)

  defp parse(<<@stx, rest::binary>> = bytes, decoder, acc) do
    parse_body(rest, bytes, :text, decoder.check, decoder, acc)
  end

  # An ETX outside a block ends one whose start was lost: its BCC, which may be any byte (EOT,
  # say), is skipped with it, never decoded.
  defp parse(<<@etx, rest::binary>>, decoder, acc) do
    acc = if decoder.state == :garbage, do: acc, else: [error(:unexpected_byte, @etx) | acc]
    parse(rest, %{decoder | state: {:skip_bcc, bcc_size(decoder.check)}}, acc)
  end

  defp parse(<<_, rest::binary>>, %{state: :garbage} = decoder, acc),
    do: parse(rest, decoder, acc)

  defp parse(<<byte, rest::binary>>, decoder, acc) do
    parse(rest, %{decoder | state: :garbage}, [error(:unexpected_byte, byte) | acc])
  end

  defp parse_dle(rest, decoder, acc) do
    case skip_del(rest) do
      <<>> -> {acc, %{decoder | buffer: <<@dle>>}}
      <<@ack0, rest::binary>> -> parse(rest, idle(decoder), [:ack0 | acc])
      <<@ack1, rest::binary>> -> parse(rest, idle(decoder), [:ack1 | acc])
      <<@wack, rest::binary>> -> parse(rest, idle(decoder), [:wack | acc])
      <<byte, _::binary>> = rest -> malformed(rest, byte, decoder, acc)
    end
  end

  defp skip_del(<<@del, rest::binary>>), do: skip_del(rest)
  defp skip_del(rest), do: rest

  defp parse_header(<<dir, check, op, @stx, body::binary>>, bytes, decoder, acc)
       when is_map_key(@direction_of, dir) and is_map_key(@check_of, check) and
              is_map_key(@operation_of, op) do
    kind = {:command, dir, check, op}
    parse_body(body, bytes, kind, Map.fetch!(@check_of, check), decoder, acc)
  end

  defp parse_header(header, bytes, decoder, acc) do
    prefix = binary_part(header, 0, min(byte_size(header), 4))

    bad =
      prefix
      |> :binary.bin_to_list()
      |> Enum.zip(@header_chars)
      |> Enum.find_index(fn {byte, allowed} -> byte not in allowed end)

    case bad do
      nil ->
        {acc, keep(decoder, bytes)}

      index ->
        # A damaged header: the block is dropped through its ETX and BCC, checked as its header
        # says when that character survived. EOT and ENQ break it off as in text (abort, block
        # abort); any other byte, a control too, is damage in place: the header positions after
        # it (its STX among them) are the block's own, not a new start.
        <<_::binary-size(index), byte, rest::binary>> = header

        check =
          case header do
            <<_dir, c, _::binary>> when is_map_key(@check_of, c) -> Map.fetch!(@check_of, c)
            _ -> decoder.check
          end

        cond do
          byte in [@eot, @enq] ->
            broken_off(byte, rest, check, decoder, acc)

          index == 3 ->
            parse(rest, %{decoder | state: {:skip, check}}, [error(:malformed, byte) | acc])

          true ->
            state = {:skip_header, 3 - index, check}
            parse(rest, %{decoder | state: state}, [error(:malformed, byte) | acc])
        end
    end
  end

  # `body` follows the STX; `bytes` is the whole block from its SOH or STX.
  defp parse_body(body, bytes, kind, check, decoder, acc) do
    max = decoder.max_text

    case :binary.match(body, @control_patterns) do
      :nomatch when byte_size(body) > max ->
        {[error(:too_long) | acc], %{decoder | state: {:skip, check}}}

      :nomatch ->
        {acc, keep(decoder, bytes)}

      {pos, 1} when pos > max ->
        <<_::binary-size(pos), rest::binary>> = body
        parse(rest, %{decoder | state: {:skip, check}}, [error(:too_long) | acc])

      {pos, 1} ->
        case body do
          <<text::binary-size(pos), @etx, rest::binary>> ->
            complete(text, rest, bytes, kind, check, decoder, acc)

          <<_::binary-size(pos), byte, rest::binary>> ->
            broken_off(byte, rest, check, decoder, acc)
        end
    end
  end

  # A control inside a block: one :malformed for the block (see the moduledoc). EOT (abort) is
  # decoded after it; anything else, ENQ included, goes with the block, whose rest is skipped.
  defp broken_off(@eot, rest, _check, decoder, acc),
    do: parse(<<@eot, rest::binary>>, idle(decoder), [error(:malformed, @eot) | acc])

  defp broken_off(byte, rest, check, decoder, acc),
    do: parse(rest, %{decoder | state: {:skip, check}}, [error(:malformed, byte) | acc])

  defp complete(text, after_etx, bytes, kind, check, decoder, acc) do
    size = bcc_size(check)

    case after_etx do
      <<received::binary-size(size), rest::binary>> ->
        covered_size = byte_size(bytes) - byte_size(after_etx) - 1
        covered = binary_part(bytes, 1, covered_size)

        if bcc(covered, check) == received do
          {frame, decoder} = accept(kind, text, decoder)
          parse(rest, idle(decoder), [frame | acc])
        else
          parse(rest, idle(decoder), [error(:bad_bcc) | acc])
        end

      _ ->
        {acc, keep(decoder, bytes)}
    end
  end

  # The text is a sub-binary of the chunk fed in: copied, so the block does not keep it alive.
  defp accept(:text, text, decoder), do: {%Text{text: :binary.copy(text)}, decoder}

  defp accept({:command, dir, check, op}, text, decoder) do
    command = %Command{
      direction: Map.fetch!(@direction_of, dir),
      check: Map.fetch!(@check_of, check),
      operation: Map.fetch!(@operation_of, op),
      text: :binary.copy(text)
    }

    {command, %{decoder | check: command.check, reverse?: command.direction == :receive}}
  end

  # A DLE followed by anything but 0, 1 or ;: decoding resumes at that byte, whose run up to the
  # next start belongs to the same trouble and is not reported again.
  defp malformed(rest, byte, decoder, acc) do
    parse(rest, %{decoder | state: :garbage}, [error(:malformed, byte) | acc])
  end

  # An unfinished block (at most max_text + 8 bytes) waits for more input as a copy of its own.
  defp keep(decoder, bytes), do: %{decoder | buffer: :binary.copy(bytes)}

  defp after_eot(%{reverse?: true} = decoder), do: %{decoder | reverse?: false, state: :idle}
  defp after_eot(decoder), do: %{decoder | check: :lrc, state: :idle}

  defp idle(decoder), do: %{decoder | state: :idle}

  defp bcc_size(:lrc), do: 1
  defp bcc_size(:crc), do: 2

  defp error(reason, byte \\ nil), do: {:error, %Error{reason: reason, byte: byte}}
end
