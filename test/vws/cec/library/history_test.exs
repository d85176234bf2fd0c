defmodule Vws.CEC.Library.HistoryTest do
  # The transfer history's file (issue 27): durable appends, rotation, records checked one by
  # one — a damaged record is skipped and told, never read as another.
  use ExUnit.Case, async: true
  use Vws.PropCase

  import ExUnit.CaptureLog
  alias Vws.CEC.Library
  alias Vws.CEC.Library.History

  setup do
    dir = Path.join(System.tmp_dir!(), "vws-history-#{System.unique_integer([:positive])}")
    on_exit(fn -> File.rm_rf!(dir) end)
    %{dir: dir}
  end

  defp record(i, extra \\ []) do
    History.new(
      [
        program: "00#{1000 + rem(i, 9000)}.PRO",
        version: rem(i, 7) + 1,
        command: "DOWNLOAD_GE(00#{1000 + rem(i, 9000)}.PRO)",
        operation: "part program",
        direction: "to machine",
        bytes: 100 + i,
        blocks: 1 + rem(i, 5),
        duration_ms: 10 * i,
        chars_per_s: 480,
        result: "DONE",
        retries: rem(i, 3),
        requester: "WC string #{i}"
      ] ++ extra
    )
  end

  test "appended records read back whole, in order, through the library's facade", %{dir: dir} do
    for i <- 1..5, do: assert(Library.record_transfer({:dir, dir}, Map.to_list(record(i))) == :ok)

    {:ok, %{records: newest_first, damaged: []}} = Library.history({:dir, dir})
    assert Enum.map(newest_first, & &1.bytes) == [105, 104, 103, 102, 101]

    {:ok, %{records: [only]}} = Library.history({:dir, dir}, program: "1003")
    assert only.program == "001003.PRO"
    assert {:ok, %{records: [_, _]}} = Library.history({:dir, dir}, limit: 2)
    assert Library.history({:dir, dir}, program: "../x") == {:error, :bad_name}
    assert Library.record_transfer("no such workstation", []) == {:error, :no_library}
  end

  test "the file is the records and one end mark: a cut anywhere, even between two records, " <>
         "is told",
       %{dir: dir} do
    records = for i <- 1..3, do: record(i)
    for r <- records, do: :ok = History.append(dir, r)
    bin = File.read!(Path.join(dir, "transfers.log"))
    assert bin == written(records)
    frame = byte_size(Vws.CEC.Journal.Log.record(hd(records)))

    capture_log(fn ->
      assert {[r1, r2], [%{why: :no_end_mark}]} = History.parse(binary_part(bin, 0, 2 * frame))
      assert [r1, r2] == Enum.take(records, 2)
    end)
  end

  test "a record that is not one is refused, nothing written", %{dir: dir} do
    assert History.append(dir, %{program: "x"}) == {:error, :not_a_record}
    assert History.append(dir, %{record(1) | bytes: "many"}) == {:error, :not_a_record}
    refute File.exists?(Path.join(dir, "transfers.log"))
  end

  test "rotation: the current file is set aside when full, at most keep + 1 files, the newest " <>
         "records kept",
       %{dir: dir} do
    frame = byte_size(Vws.CEC.Journal.Log.record(record(1)))
    opts = [max_bytes: frame * 10, keep: 2]
    for i <- 1..100, do: :ok = History.append(dir, record(i), opts)

    files = File.ls!(dir) |> Enum.sort()
    assert files == ["transfers.1.log", "transfers.2.log", "transfers.log"]
    for f <- files, do: assert(File.stat!(Path.join(dir, f)).size <= frame * 10 + 100)

    %{records: records, damaged: []} = History.read(dir)
    ids = Enum.map(records, & &1.bytes)
    # the newest ones, oldest first, none missing between them
    assert List.last(ids) == 200
    assert ids == Enum.to_list(hd(ids)..200)
    assert length(ids) >= 16

    # the newest n read from the newest files only
    %{records: newest} = History.read(dir, 3)
    assert length(newest) < length(records)
    assert Enum.take(Enum.map(newest, & &1.bytes), -3) == [198, 199, 200]
  end

  test "the default bound is documented and one record is far below it" do
    assert History.defaults() == [max_bytes: 1_048_576, keep: 4]
    assert byte_size(Vws.CEC.Journal.Log.record(record(1))) < 1_000
  end

  test "a torn last record (a kill in the middle of an append) is told, and the next append " <>
         "begins a new file so it hides nothing",
       %{dir: dir} do
    for i <- 1..3, do: :ok = History.append(dir, record(i))
    path = Path.join(dir, "transfers.log")
    good = File.read!(path)
    torn = binary_part(Vws.CEC.Journal.Log.record(record(4)), 0, 40)
    File.write!(path, good <> torn)

    log =
      capture_log(fn ->
        :ok = History.append(dir, record(5))
        %{records: records, damaged: damaged} = History.read(dir)
        assert Enum.map(records, & &1.bytes) == [101, 102, 103, 105]
        assert [%{file: "transfers.1.log", why: why}] = damaged
        assert why in [:cut_short, :no_end_mark]
      end)

    assert log =~ "transfer history"
    assert log =~ "skipped"
  end

  test "a damaged record in the middle is skipped loudly, the others read", %{dir: dir} do
    for i <- 1..3, do: :ok = History.append(dir, record(i))
    path = Path.join(dir, "transfers.log")
    bin = File.read!(path)
    frame = byte_size(Vws.CEC.Journal.Log.record(record(1)))
    # a bit of the second record's payload
    at = frame + 40
    <<pre::binary-size(at), b, post::binary>> = bin
    File.write!(path, <<pre::binary, Bitwise.bxor(b, 4), post::binary>>)

    log =
      capture_log(fn ->
        %{records: records, damaged: [d]} = History.read(dir)
        assert Enum.map(records, & &1.bytes) == [101, 103]
        assert d.why == :bad_checksum
        assert d.offset == frame
      end)

    assert log =~ "offset #{frame}"
  end

  ## Properties

  defp record_gen do
    text = :proper_types.list(:proper_types.range(32, 126))
    int = :proper_types.non_neg_integer()

    :proper_types.tuple([
      int,
      text,
      int,
      int,
      :proper_types.oneof([:proper_types.exactly(nil), :proper_types.pos_integer()]),
      :proper_types.elements(["DONE", "ERROR PROGRAM VERIFY FAILED 000001.PRO", "ERROR DNC NAK"])
    ])
  end

  defp to_record({bytes, requester, retries, ms, version, result}) do
    record(1,
      bytes: bytes,
      requester: List.to_string(requester),
      retries: retries,
      duration_ms: ms,
      version: version,
      result: result
    )
  end

  test "property: random records survive the round trip, in order", %{dir: dir} do
    property =
      :proper.forall(:proper_types.list(record_gen()), fn specs ->
        records = Enum.map(specs, &to_record/1)

        bin = written(records)

        {read, damaged} = History.parse(bin)

        read == records and damaged == []
      end)

    assert_property(property, 300)
    _ = dir
  end

  defp damage_gen(size) do
    :proper_types.oneof([
      :proper_types.tuple([:proper_types.exactly(:flip), :proper_types.range(0, size * 8 - 1)]),
      :proper_types.tuple([:proper_types.exactly(:cut), :proper_types.range(0, size - 1)]),
      :proper_types.tuple([
        :proper_types.exactly(:zero),
        :proper_types.range(0, size - 1),
        :proper_types.range(1, 64)
      ]),
      :proper_types.tuple([
        :proper_types.exactly(:random),
        :proper_types.range(0, size - 1),
        :proper_types.binary()
      ])
    ])
  end

  defp damage(bin, {:flip, bit}) do
    <<pre::bitstring-size(bit), b::1, post::bitstring>> = bin
    <<pre::bitstring, 1 - b::1, post::bitstring>>
  end

  defp damage(bin, {:cut, at}), do: binary_part(bin, 0, at)

  defp damage(bin, {:zero, at, n}) do
    n = min(n, byte_size(bin) - at)
    <<pre::binary-size(at), _::binary-size(n), post::binary>> = bin
    <<pre::binary, 0::size(n)-unit(8), post::binary>>
  end

  defp damage(bin, {:random, at, bytes}) do
    n = min(byte_size(bytes), byte_size(bin) - at)
    <<pre::binary-size(at), _::binary-size(n), post::binary>> = bin
    <<pre::binary, binary_part(bytes, 0, n)::binary, post::binary>>
  end

  test "property: random damage never yields a wrong record — every record read is one that " <>
         "was written, in order, and damage is told",
       %{dir: dir} do
    property =
      :proper.forall(:proper_types.non_empty(:proper_types.list(record_gen())), fn specs ->
        records = Enum.map(specs, &to_record/1)

        bin = written(records)

        :proper.forall(:proper_types.list(damage_gen(byte_size(bin))), fn damages ->
          damaged_bin =
            Enum.reduce(damages, bin, fn d, acc ->
              if byte_size(acc) == 0 or
                   elem(d, 1) >= byte_size(acc) * if(elem(d, 0) == :flip, do: 8, else: 1),
                 do: acc,
                 else: damage(acc, d)
            end)

          {read, told} = History.parse(damaged_bin)

          # never misread: what is read is a subsequence of what was written (every record
          # is different: its id); and never silent: a record lost is told
          subsequence?(read, records) and (read == records or told != [])
        end)
      end)

    assert_property(property, 300)
    _ = dir
  end

  # a history file as the appends write it: the records, then one end mark
  defp written(records),
    do:
      IO.iodata_to_binary([
        for(r <- records, do: Vws.CEC.Journal.Log.record(r)),
        Vws.CEC.Journal.Log.end_mark()
      ])

  defp subsequence?([], _), do: true
  defp subsequence?(_, []), do: false
  defp subsequence?([a | as], [a | bs]), do: subsequence?(as, bs)
  defp subsequence?(as, [_ | bs]), do: subsequence?(as, bs)
end
