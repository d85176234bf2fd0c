defmodule Vws.Reliability.WCProgramCRCTest do
  @moduledoc """
  The whole-program check of DOWNLOAD_HP (issue 24 D, PROTOCOLS.md §1 "Whole-program check"),
  end to end over a real TCP link to a workstation's SUN_COMM.

  Each program line carries only the 8-bit-sum BCC; two bits of one line flipped in opposite
  directions (one set, the same bit cleared in another byte) keep the sum, and such a line is
  stored as it came. With the program's CRC named in `DOWNLOAD_HP(cccc)`, SUN_COMM must never end
  DONE with other bytes: a random program, with random damage to random lines on their first
  transmission (random bit flips, and two-bit patterns the BCC cannot see), ends DONE with the
  program exactly, or ERROR with the NC file as it was — and when the only damage is what the
  BCC cannot see, the ERROR is `PROGRAM CRC <what came> EXPECTED <what was named>`.
  """
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.CEC.{Mailbox, SunComm}
  alias Vws.Codecs.WC.{BCC, Command, ProgramCRC, Reply}
  alias Vws.Test.{WCPeer, Workstation}

  @moduletag timeout: 600_000

  @old ["%", "O000001", "N10 M30", "%"]
  # the characters of the generated NC lines: neither `%` nor any pair of bytes that two
  # sum-keeping flips could turn into a line `%` (so a damaged line never ends the program)
  @alphabet ~c"ABCDFGIJKLMNOPRSTXYZ0123456789 .-+()"

  setup do
    %{ws: ws} = Workstation.start(wc: "tcp://127.0.0.1:0")
    {:ok, peer} = WCPeer.connect(await_listening(ws))
    %{ws: ws, peer: peer, runs: :counters.new(1, [])}
  end

  defp await_listening(ws) do
    case SunComm.listening(ws) do
      nil -> Process.sleep(10) && await_listening(ws)
      endpoint -> to_string(endpoint)
    end
  end

  ## Generators

  defp nc_line do
    :proper_types.bind(
      :proper_types.non_empty(:proper_types.list(:proper_types.elements(@alphabet))),
      fn chars -> :proper_types.exactly(List.to_string(chars)) end,
      false
    )
  end

  defp program do
    :proper_types.bind(
      :proper_types.tuple([
        :proper_types.range(1, 999_999),
        :proper_types.resize(12, :proper_types.list(nc_line()))
      ]),
      fn {number, body} ->
        :proper_types.exactly(["%", "O#{number}"] ++ body ++ ["%"])
      end,
      false
    )
  end

  # `{line r, kind, r, bit}`: the line damaged (r modulo the program's length), how, and the
  # random numbers that choose the bytes and the bit
  defp damage(kinds) do
    :proper_types.list(
      :proper_types.tuple([
        :proper_types.range(0, 1_000_000),
        :proper_types.elements(kinds),
        :proper_types.range(0, 1_000_000),
        :proper_types.range(0, 6)
      ])
    )
  end

  ## Damage

  # Two bits of the line's text (not its number, not its BCC) flipped, the same bit set in one
  # byte and cleared in another, both still printable: the BCC cannot see it. nil when the line
  # has no such pair.
  defp sum_keeping(wire, r, bit) do
    mask = Bitwise.bsl(1, bit)
    size = byte_size(wire) - 3
    <<number::binary-4, text::binary-size(size - 4), bcc::binary-3>> = wire
    bytes = :binary.bin_to_list(text)
    printable = &(Bitwise.bxor(&1, mask) in 0x20..0x7E)
    indexed = Enum.with_index(bytes)
    ones = for {b, i} <- indexed, Bitwise.band(b, mask) != 0, printable.(b), do: i
    zeros = for {b, i} <- indexed, Bitwise.band(b, mask) == 0, printable.(b), do: i

    if ones != [] and zeros != [] do
      a = Enum.at(ones, rem(r, length(ones)))
      z = Enum.at(zeros, rem(div(r, 13), length(zeros)))

      flipped =
        bytes
        |> List.update_at(a, &Bitwise.bxor(&1, mask))
        |> List.update_at(z, &Bitwise.bxor(&1, mask))

      damaged = number <> :binary.list_to_bin(flipped)
      true = BCC.compute(damaged) == BCC.compute(number <> text)
      damaged <> bcc
    end
  end

  # One to three bits flipped anywhere in the line (number, text, BCC digits); a flip that would
  # make a CR or LF (the line cut in two: framing, covered by wc_bit_flip_test) is left out.
  defp random_bits(wire, r, _bit) do
    flips = rem(r, 3) + 1

    Enum.reduce(1..flips, wire, fn k, acc ->
      seed = div(r, k * 7 + 1)
      i = rem(seed, byte_size(acc))
      mask = Bitwise.bsl(1, rem(div(seed, 11), 8))
      <<before::binary-size(i), b, rest::binary>> = acc
      new = Bitwise.bxor(b, mask)
      if new in [?\r, ?\n], do: acc, else: <<before::binary, new, rest::binary>>
    end)
  end

  # line number (1-based) → the bytes of its first transmission
  defp plan(program, damages) do
    n = length(program)

    Enum.reduce(damages, %{}, fn {line_r, kind, r, bit}, plan ->
      line = rem(line_r, n) + 1
      wire = wire(line, Enum.at(program, line - 1))

      damaged =
        case kind do
          :sum_keeping -> sum_keeping(wire, r, bit)
          :random_bits -> random_bits(wire, r, bit)
        end

      if damaged && damaged != wire, do: Map.put(plan, line, damaged), else: plan
    end)
  end

  defp wire(n, text),
    do: IO.iodata_to_binary(Reply.encode({:line, rem(n, 10_000), text})) |> String.trim_trailing()

  ## The WC

  # DOWNLOAD_HP(cccc) (or the seed's DOWNLOAD_HP), then the lines: a planned damage on a line's
  # first transmission; any answer but the one awaited sends the clean line again, at most
  # three times, then the WC gives up. Returns the Monarch command's final status text.
  defp download(ctx, program, plan, named?) do
    :counters.add(ctx.runs, 1, 1)
    run = :counters.get(ctx.runs, 1)
    {seq, number} = {rem(run * 2, 9_998) + 1, rem(run, 9_998) + 1}
    command = if named?, do: "DOWNLOAD_HP(#{hex(program)})", else: "DOWNLOAD_HP"
    WCPeer.send_string(ctx.peer, seq, [{"M", number, command}])
    assert {:ok, {:ack, ^seq}} = Reply.decode(WCPeer.recv_line(ctx.peer))

    Enum.reduce_while(Enum.with_index(program, 1), :ok, fn {text, n}, :ok ->
      clean = wire(n, text)
      first = Map.get(plan, n, clean)
      expected = WCPeer.download_answer(program, n)

      case send_line(ctx.peer, first, clean, expected, 0) do
        :ok -> {:cont, :ok}
        :gave_up -> {:halt, :gave_up}
      end
    end)

    # a WC that gave up asks the status: the string ends a download still under way, ERROR
    status =
      WCPeer.await_status(
        ctx.peer,
        35,
        "MONARCH_CMD",
        &(String.starts_with?(&1, Command.pad4(number)) and not (&1 =~ "EXECUTING")),
        10_000
      )

    <<prefix::binary-4, word::binary>> = status
    assert prefix == Command.pad4(number), "status #{status}"
    word
  end

  defp send_line(peer, bytes, clean, expected, tries) do
    WCPeer.send_raw(peer, bytes <> "\r\n")

    case WCPeer.recv_line(peer) do
      answer when is_binary(answer) ->
        cond do
          Reply.decode(answer) == {:ok, expected} -> :ok
          tries < 3 -> send_line(peer, clean, clean, expected, tries + 1)
          true -> :gave_up
        end

      _timeout ->
        :gave_up
    end
  end

  defp hex(program), do: ProgramCRC.format(ProgramCRC.compute(program))

  # DONE: the NC file is the program, or other bytes with the same CRC-16 (what the check, 16
  # bits, cannot tell apart) — never other bytes with another CRC
  defp done_with?(ws, program) do
    stored = Mailbox.nc_file(ws)
    stored == program or hex(stored) == hex(program)
  end

  test "a CRC-16 collision of two sum-keeping damages is what the whole-program check cannot see" do
    # found by the property below: "B@CABB" and "ACA@" for "BABABB" and "ABAA" keep every line's
    # BCC and the program's CRC-16/ARC
    program = ["%", "O1", "A", "A", "BABABB", "AAAAAA", "ABAA", "%"]
    arrived = ["%", "O1", "A", "A", "B@CABB", "AAAAAA", "ACA@", "%"]
    assert hex(arrived) == hex(program)

    for {a, b} <- Enum.zip(program, arrived),
        do: assert(BCC.compute(a) == BCC.compute(b))
  end

  ## Properties

  test "random damage on random lines, the CRC named: DONE with the program exactly, or ERROR " <>
         "with the old NC file — never DONE with other bytes",
       ctx do
    outcomes = :ets.new(:outcomes, [:public, :duplicate_bag])

    property =
      :proper.forall(
        :proper_types.tuple([program(), damage([:sum_keeping, :random_bits])]),
        fn {program, damages} ->
          :ok = Mailbox.put_nc_file(ctx.ws, @old)
          plan = plan(program, damages)
          word = download(ctx, program, plan, true)
          :ets.insert(outcomes, {word == "DONE", map_size(plan)})

          cond do
            # the program exactly — or other bytes only where their CRC-16 is the one named
            # (a collision: beyond what a 16-bit check can see, about 1 in 65,536 damages)
            word == "DONE" -> done_with?(ctx.ws, program)
            String.starts_with?(word, "ERROR ") -> Mailbox.nc_file(ctx.ws) == @old
            true -> false
          end
        end
      )

    assert_property(property, 150)
    # both ends were reached: damaged programs refused, and programs sent whole (an undamaged
    # one, or one whose damage the BCC saw and a resend mended)
    assert :ets.match(outcomes, {true, :_}) != []
    assert :ets.match(outcomes, {false, :_}) != []
  end

  test "damage the BCC cannot see ends ERROR PROGRAM CRC <what came> EXPECTED <what was named>; " <>
         "no damage ends DONE",
       ctx do
    property =
      :proper.forall(
        :proper_types.tuple([program(), damage([:sum_keeping])]),
        fn {program, damages} ->
          :ok = Mailbox.put_nc_file(ctx.ws, @old)
          plan = plan(program, damages)
          word = download(ctx, program, plan, true)

          # what SUN_COMM stored: every damaged line as it came (its BCC held)
          arrived =
            for {text, n} <- Enum.with_index(program, 1) do
              case plan do
                %{^n => damaged} ->
                  {:ok, {:line, _, t}} = Reply.decode_line(damaged)
                  t

                _ ->
                  text
              end
            end

          cond do
            plan == %{} ->
              word == "DONE" and Mailbox.nc_file(ctx.ws) == program

            # damage whose CRC-16 is the program's (a collision, about 1 in 65,536: seen once,
            # two sum-keeping pairs in "BABABB" and "ABAA"): the check cannot see it
            hex(arrived) == hex(program) ->
              word == "DONE" and Mailbox.nc_file(ctx.ws) == arrived

            true ->
              word == "ERROR PROGRAM CRC #{hex(arrived)} EXPECTED #{hex(program)}" and
                Mailbox.nc_file(ctx.ws) == @old
          end
        end
      )

    assert_property(property, 150)
  end

  test "UPLOAD_SUN: the closing %/cccc is checked by the WC client — random damage on a random " <>
         "line ends with the program exactly or a :program_crc error, never other lines",
       ctx do
    # the client over a relay that damages one chosen line on its way to the WC (it takes the
    # WC link from the bare peer of the other tests)
    WCPeer.close(ctx.peer)
    name = "crc-relay-#{System.unique_integer([:positive])}"
    {:ok, relay} = Vws.Test.LineRelay.start_link(await_listening(ctx.ws), name)
    {:ok, client} = Vws.Peers.WC.Client.connect("loopback:" <> name, line_timeout: 300)
    outcomes = :ets.new(:outcomes, [:public, :duplicate_bag])

    property =
      :proper.forall(
        :proper_types.tuple([
          program(),
          :proper_types.range(0, 1_000_000),
          :proper_types.elements([:none, :sum_keeping]),
          :proper_types.range(0, 1_000_000),
          :proper_types.range(0, 6)
        ]),
        fn {program, line_r, kind, r, bit} ->
          :ok = Mailbox.put_nc_up(ctx.ws, program)
          # a body line (the closing one carries the CRC and is checked by it alike)
          n = rem(line_r, length(program) - 1) + 1
          wire = wire(n, Enum.at(program, n - 1))
          damaged = if kind == :sum_keeping, do: sum_keeping(wire, r, bit)

          if damaged,
            do:
              :ok =
                Vws.Test.LineRelay.arm(
                  relay,
                  :to_wc,
                  {:replace, fn _ -> damaged end},
                  &(&1 == wire)
                )

          result = Vws.Peers.WC.Client.upload_program(client)
          :ets.insert(outcomes, {elem(result, 0), damaged != nil})

          case result do
            {:ok, _command, lines} ->
              damaged == nil and lines == program

            {:error, %Vws.Peers.WC.ClientError{reason: :program_crc, data: data}} ->
              damaged != nil and data.direction == :upload and
                data.sent == ProgramCRC.compute(program) and data.stored != data.sent

            other ->
              IO.puts("unexpected: #{inspect(other)}")
              false
          end
        end
      )

    assert_property(property, 80)
    assert :ets.match(outcomes, {:ok, false}) != []
    assert :ets.match(outcomes, {:error, true}) != []
  end

  test "why: without the CRC (the seed's DOWNLOAD_HP) the same damage ends DONE with other bytes",
       ctx do
    program = ["%", "O001234", "N10 G90 G00 X0 Y0", "N20 M30", "%"]
    damaged = sum_keeping(wire(3, Enum.at(program, 2)), 0, 0)
    assert {:ok, {:line, 3, text}} = Reply.decode_line(damaged)
    assert text != Enum.at(program, 2)

    :ok = Mailbox.put_nc_file(ctx.ws, @old)
    assert download(ctx, program, %{3 => damaged}, false) == "DONE"
    assert Mailbox.nc_file(ctx.ws) == List.replace_at(program, 2, text)

    :ok = Mailbox.put_nc_file(ctx.ws, @old)

    assert download(ctx, program, %{3 => damaged}, true) ==
             "ERROR PROGRAM CRC #{hex(List.replace_at(program, 2, text))} EXPECTED #{hex(program)}"

    assert Mailbox.nc_file(ctx.ws) == @old
  end
end
