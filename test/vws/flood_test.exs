defmodule Vws.FloodTest do
  @moduledoc """
  Bounded memory (issue 8, item 4): a peer that floods garbage, or starts a frame and never ends
  it, cannot grow any buffer. Every decoder is fed tens of megabytes in 64 KB chunks and its
  buffer is checked against its documented bound after every chunk; then the live WC link on
  both sides — SUN_COMM and the WC client — takes 20 MB and its process stays small and answers.

  The byte-at-a-time decoders (DDCMP, DNC) get 16 MB of random garbage rather than 50: they hold
  their bound from the first kilobytes, and 50 MB would cost seconds more of a shared machine.
  """
  use ExUnit.Case, async: true

  alias Vws.Links.{DDCMP, DNC, Transport}
  alias Vws.Codecs.SCPI
  alias Vws.Test.{ObedientPartition, WCPeer, Workstation}
  alias Vws.Peers.WC.Client
  alias Vws.Codecs.WC.LineDecoder
  import Vws.Test.Eventually

  @chunk 65_536
  @mb div(1_048_576, @chunk)

  # 1 MB of fixed pseudo-random bytes; chunks are cut from it at moving offsets.
  @block elem(:rand.bytes_s(1_048_576, :rand.seed_s(:exsss, {8, 4, 1988})), 0)
  @filler :binary.copy("A", @chunk)

  defp garbage(megabytes) do
    Stream.map(1..(megabytes * @mb), fn i ->
      # a copy, as a transport delivers it, not a slice of the block
      :binary.copy(binary_part(@block, rem(i * 4_099, byte_size(@block) - @chunk), @chunk))
    end)
  end

  # `prefix` starts a frame; `megabytes` of `filler` never end it.
  defp endless(prefix, megabytes, filler \\ @filler),
    do: Stream.concat([prefix], Stream.duplicate(filler, megabytes * @mb))

  # Feeds every chunk; after each, the decoder's buffer stays under `bound`, and the memory its
  # binaries reference under `bound` plus the last chunk (a buffer may be a slice of it).
  # Returns the decoder and how many frames and errors came out.
  defp flood(decoder, feed, buffered, bound, stream) do
    Enum.reduce(stream, {decoder, 0}, fn chunk, {decoder, out} ->
      {items, decoder} = feed.(decoder, chunk)
      size = buffered.(decoder)
      assert size <= bound, "#{size} bytes buffered, bound #{bound}"
      assert held(decoder) <= bound + @chunk
      assert :erlang.external_size(decoder) <= bound + 1_024
      {decoder, out + length(items)}
    end)
  end

  defp held(decoder) do
    decoder
    |> Map.from_struct()
    |> Map.values()
    |> Enum.filter(&is_binary/1)
    |> Enum.map(&:binary.referenced_byte_size/1)
    |> Enum.sum()
  end

  describe "decoders" do
    test "WC line decoder: 50 MB of garbage, 50 MB of a line that never ends" do
      bound = 1_024 + 1
      feed = &LineDecoder.feed/2
      flood(LineDecoder.new(), feed, &LineDecoder.buffered/1, bound, garbage(50))

      # the endless line is one error, as soon as it is too long (issue 15)
      {dec, 1} =
        flood(LineDecoder.new(), feed, &LineDecoder.buffered/1, bound, endless("*0001*R0001", 50))

      # once it ends, the next line is read as usual
      assert {["*0002*S0001ROBOT_CMD*013"], _} =
               LineDecoder.feed(dec, "\r\n*0002*S0001ROBOT_CMD*013\r\n")
    end

    test "WC line decoder: a line out of a megabyte chunk does not keep the megabyte" do
      chunk = :binary.copy("A", 1_048_576) <> "\r\n" <> :binary.copy("L", 500) <> "\r\nTAIL"
      {[{:error, _}, line], dec} = LineDecoder.feed(LineDecoder.new(), chunk)
      assert :binary.referenced_byte_size(line) == 500
      assert held(dec) == 4
    end

    test "DDCMP: garbage, a flood of SOH, and a message that announces more than it sends" do
      max_data = 4_096
      bound = 8 + max_data + 2
      feed = &DDCMP.Frame.feed/2
      buffered = &DDCMP.Frame.buffered_bytes/1
      flood(DDCMP.Frame.new(), feed, buffered, bound, garbage(16))

      # every byte a class byte whose header never checks (about 3 µs a byte: kept short)
      flood(
        DDCMP.Frame.new(),
        feed,
        buffered,
        bound,
        Stream.duplicate(:binary.copy(<<0x81>>, 16_384), 16)
      )

      # a good header announcing the largest message accepted, then filler with no class byte
      header = max_data |> header() |> binary_part(0, 8)
      flood(DDCMP.Frame.new(), feed, buffered, bound, endless(header, 50))

      # one announcing more than max_data: skipped as it comes, never buffered
      flood(
        DDCMP.Frame.new(),
        feed,
        buffered,
        bound,
        endless(binary_part(header(0x3FFF), 0, 8), 16)
      )
    end

    test "DNC: garbage, and text blocks that never reach their ETX" do
      bound = 256 + 8
      feed = &DNC.Frame.feed/2
      buffered = fn dec -> byte_size(dec.buffer) end
      flood(DNC.Frame.new(), feed, buffered, bound, garbage(16))
      flood(DNC.Frame.new(), feed, buffered, bound, endless(<<0x02>>, 16))
      # a command block: SOH S N S STX and then no end
      flood(DNC.Frame.new(), feed, buffered, bound, endless(<<0x01, "SNS", 0x02>>, 16))
    end

    test "SCPI line decoder: 50 MB of garbage, 50 MB of a line that never ends" do
      bound = 4_096
      buffered = fn dec -> byte_size(dec.buffer) end
      flood(SCPI.new(), &SCPI.feed/2, buffered, bound, garbage(50))

      # reported once, as soon as it is too long
      {dec, 1} =
        flood(
          SCPI.new(),
          &SCPI.feed/2,
          buffered,
          bound,
          endless("MEAS:VOLT:DC? (@", 50, :binary.copy("1", @chunk))
        )

      assert {["*IDN?"], _} = SCPI.feed(dec, "\n*IDN?\n")
    end
  end

  defp header(count) do
    # the encoder refuses COUNT above 0x3FFF, the field's width; any data of that size will do
    DDCMP.Frame.data(0, 0, :binary.copy(<<0>>, count))
    |> DDCMP.Frame.encode()
    |> IO.iodata_to_binary()
  end

  # Process memory plus the off-heap binaries it holds, after a full collection.
  defp footprint(pid) do
    :erlang.garbage_collect(pid)

    [memory: memory, binary: binaries, message_queue_len: queue] =
      Process.info(pid, [:memory, :binary, :message_queue_len])

    {memory + Enum.sum(for {_id, size, _refs} <- binaries, do: size), queue}
  end

  # Sends every chunk of `stream` through `send`, measuring `pid` after every `every` sends;
  # returns the largest footprint seen.
  # the client's stray count once it has read everything sent to it
  defp settled_stray(client, last \\ nil) do
    Process.sleep(100)

    case Client.info(client).counters.stray do
      ^last -> last
      now -> settled_stray(client, now)
    end
  end

  defp flood_process(pid, send, stream, every \\ @mb) do
    stream
    |> Stream.with_index(1)
    |> Enum.reduce(0, fn {chunk, i}, worst ->
      :ok = send.(chunk)

      if rem(i, every) == 0 do
        {bytes, queue} = footprint(pid)
        assert queue <= 2, "#{queue} messages waiting"
        max(worst, bytes)
      else
        worst
      end
    end)
  end

  # What a flooded WC-link process may hold: its bounded log (SUN_COMM's dialogue keeps 200 lines,
  # the client's event log 1 000), one loopback delivery in its mailbox (about 1 MB) and the lines
  # of the one it is working on.
  @process_bound 8 * 1_048_576
  @megabyte :binary.copy("A", 1_048_576)

  # A megabyte-long line, then a 500-byte line that the receiver keeps in its log: before lines
  # were copied out of the chunk they came in, each kept line kept its megabyte too.
  defp pinning(times),
    do: Stream.duplicate([@megabyte, "\r\n", :binary.copy("P", 500), "\r\n"], times)

  describe "the WC link" do
    test "SUN_COMM takes 20 MB without a LF and 16 MB of pinning lines in bounded memory" do
      %{ws: ws, wc: wc} = Workstation.start(partitions: ObedientPartition.partitions())
      assert eventually(fn -> Vws.CEC.SunComm.listening(ws) != nil end)
      sun_comm = GenServer.whereis(Vws.Names.via(ws, :sun_comm))
      {:ok, peer} = WCPeer.connect(wc)

      noise = Stream.map(garbage(20), &:binary.replace(&1, "\n", " ", [:global]))
      worst = flood_process(sun_comm, &WCPeer.send_raw(peer, &1), noise)
      assert worst < @process_bound, "SUN_COMM held #{worst} bytes"

      # the endless line ends: one E; then the link works as ever
      :ok = WCPeer.send_raw(peer, "\r\n")
      assert WCPeer.recv_line(peer) == "E"
      assert WCPeer.status(peer, 1, 1, "ROBOT_CMD") == "0000NONE"

      worst = flood_process(sun_comm, &WCPeer.send_raw(peer, &1), pinning(16), 1)
      assert worst < @process_bound, "SUN_COMM held #{worst} bytes"
      # each megabyte line and each 500-byte line is answered E
      assert Enum.map(1..32, fn _ -> WCPeer.recv_line(peer) end) == List.duplicate("E", 32)
      assert WCPeer.status(peer, 2, 2, "ROBOT_CMD") == "0000NONE"
    end

    test "the WC client takes 20 MB of garbage and 16 MB of pinning lines in bounded memory" do
      name = "flood-cec-#{System.unique_integer([:positive])}"
      {:ok, listener} = Transport.listen("loopback:#{name}")
      {:ok, client} = Client.connect("loopback:#{name}", reply_timeout: 2_000)
      {:ok, cec} = Transport.accept(listener, 5_000)
      send = &Transport.send(cec, &1)

      worst = flood_process(client, send, garbage(10))
      # end the garbage's last line (it may be too long already, and reported so)
      :ok = Transport.send(cec, "\r\n")
      stray = settled_stray(client)
      worst = max(worst, flood_process(client, send, endless("13S", 10)))
      assert worst < @process_bound, "the client held #{worst} bytes"

      # the endless line: one damaged line for the client as soon as it is too long; its end
      # adds nothing
      :ok = Transport.send(cec, "\r\n")
      assert eventually(fn -> Client.info(client).counters.stray == stray + 1 end)

      worst = flood_process(client, send, pinning(16), 1)
      assert worst < @process_bound, "the client held #{worst} bytes"
      assert eventually(fn -> Client.info(client).counters.stray == stray + 1 + 32 end)

      # and it still talks: the CEC answers a status query
      asker = Task.async(fn -> Client.status(client, "VACUUM") end)
      :ok = Transport.activate(cec)
      assert_receive {:vws_loopback, _, query}, 5_000
      assert query =~ ~r/^\*0001\*S0001VACUUM\*\d{3}\r\n$/
      :ok = Transport.send(cec, ["17S0001VACUUM IS ON", bcc("17S0001VACUUM IS ON"), "\r\n"])
      assert Task.await(asker) == {:ok, "VACUUM IS ON"}
    end
  end

  defp bcc(text),
    do:
      text
      |> :binary.bin_to_list()
      |> Enum.sum()
      |> rem(256)
      |> Integer.to_string()
      |> String.pad_leading(3, "0")
end
