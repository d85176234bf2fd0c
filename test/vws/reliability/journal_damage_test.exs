defmodule Vws.Reliability.JournalDamageTest do
  # Issue 30, "Damage is loud, never silent": a journal damaged at a random point — bit flips,
  # a cut anywhere, zeroed or random blocks, a record torn by a full disk or a power loss while it
  # was written — restores every status as it was or says it is unknown; never an older one.
  use ExUnit.Case, async: true
  use Vws.PropCase

  import :proper_types

  alias Vws.CEC.{Journal, Mailbox}
  alias Vws.CEC.Journal.{Log, Replay}

  @moduletag :tmp_dir
  # the properties write and sync hundreds of journals: under the whole suite's disk traffic
  # 300 cases took more than ExUnit's default minute
  @moduletag timeout: 300_000

  @partitions Mailbox.partitions()
  @letters ["Q", "X", "Z"]

  ## The journal process itself, on a real directory

  defp start(id, dir, every) do
    start_supervised!({Mailbox.Owner, workstation: id}, id: {:owner, id})

    start_supervised!({Journal, workstation: id, dir: dir, snapshot_every: every},
      id: {:journal, id}
    )
  end

  defp stop(id) do
    :ok = stop_supervised({:journal, id})
    :ok = stop_supervised({:owner, id})
  end

  defp status, do: elements([:done, {:error, "NO LINK"}, {:error, "BUSY 0001"}, :none])

  # What the live system does to the mailboxes (each change recorded first, as SUN_COMM, the
  # partitions and the interlock do): dispatches, ends, rule errors, strings, unknown letters,
  # leases.
  defp op do
    oneof([
      tuple([exactly(:dispatch), elements(@partitions), range(0, 9999)]),
      tuple([exactly(:finish), elements(@partitions), status()]),
      tuple([exactly(:put_status), elements(@partitions), range(0, 9999), status()]),
      tuple([exactly(:unknown), elements(@letters), range(0, 9999)]),
      tuple([
        exactly(:string),
        range(0, 9999),
        list(tuple([elements(@partitions), range(0, 9999)]))
      ]),
      tuple([
        exactly(:lease),
        elements([:table, :tray1]),
        elements([:robot, :fixture]),
        list(elements([:inside, :vise]))
      ])
    ])
  end

  defp run(id, {:dispatch, p, n}), do: Mailbox.dispatch(id, p, n, "CMD #{n}")

  defp run(id, {:finish, p, status}) do
    case Mailbox.in_flight(id, p) do
      nil -> :ok
      n -> Mailbox.finish(id, p, n, if(status == :none, do: :done, else: status))
    end
  end

  defp run(id, {:put_status, p, n, status}), do: Mailbox.put_status(id, p, n, status)

  defp run(id, {:unknown, l, n}),
    do: Mailbox.put_unknown_status(id, l, n, {:error, "UNKNOWN COMMAND SET #{l}"})

  defp run(id, {:string, seq, commands}) do
    commands = Enum.uniq_by(commands, &elem(&1, 0))
    line = "*#{seq}*" <> Enum.map_join(commands, "*", fn {p, n} -> "#{p}#{n}" end)
    :ok = Journal.record(Mailbox.table(id), {:string, seq, line, commands})
    Mailbox.put_last_string(id, seq, line)

    for {p, n} <- commands do
      case Mailbox.dispatch(id, p, n, "CMD #{n}") do
        {:busy, m} -> Mailbox.put_status(id, p, n, {:error, "BUSY #{m}"})
        :ok -> :ok
      end
    end
  end

  defp run(id, {:lease, v, h, reasons}),
    do: :ok = Mailbox.record(Mailbox.table(id), {:lease, v, h, Enum.uniq(reasons)})

  # Damage as a disk does it, at a random place (`at` taken modulo the file's size).
  defp damage do
    oneof([
      tuple([exactly(:flip), range(0, 1_000_000), range(0, 7)]),
      tuple([exactly(:cut), range(0, 1_000_000)]),
      tuple([exactly(:zero), range(0, 1_000_000), range(1, 600)]),
      tuple([exactly(:random), range(0, 1_000_000), binary()]),
      # one more record torn while it was written (its change never shown): a full disk, a
      # power loss
      tuple([exactly(:torn), range(1, 60)]),
      # none: everything restores exactly
      exactly(:none)
    ])
  end

  defp damaged(bin, {:flip, at, bit}) do
    at = rem(at, byte_size(bin))
    <<a::binary-size(at), b, rest::binary>> = bin
    <<a::binary, Bitwise.bxor(b, Bitwise.bsl(1, bit)), rest::binary>>
  end

  defp damaged(bin, :none), do: bin

  defp damaged(bin, {:cut, at}), do: binary_part(bin, 0, rem(at, byte_size(bin)))

  defp damaged(bin, {:zero, at, len}),
    do: overwrite(bin, rem(at, byte_size(bin)), :binary.copy(<<0>>, len))

  defp damaged(bin, {:random, at, bytes}) do
    bytes = if bytes == "", do: <<0xA5>>, else: bytes
    overwrite(bin, rem(at, byte_size(bin)), bytes)
  end

  defp damaged(bin, {:torn, len}) do
    frame = Log.record({:finish, :vacuum, 1, :done})

    binary_part(bin, 0, byte_size(bin) - byte_size(Log.end_mark())) <>
      binary_part(frame, 0, min(len, byte_size(frame) - 1))
  end

  # the bytes from `at` replaced, the file's length kept
  defp overwrite(bin, at, bytes) do
    len = min(byte_size(bytes), byte_size(bin) - at)
    <<a::binary-size(at), _::binary-size(len), rest::binary>> = bin
    <<a::binary, binary_part(bytes, 0, len)::binary, rest::binary>>
  end

  # true, or unknown: never another (older) value. A command status is unknown as
  # `NO DATA (…)`; CMD_IN (the text of the last command, which the WC never reads back) as nil.
  defp true_or_unknown(restored, truth) do
    bad_partitions =
      for p <- @partitions,
          r = restored.partitions[p],
          t = truth.partitions[p],
          {r.number, r.status} != {t.number, t.status} and
            not match?(%{number: nil, status: {:no_data, _}}, r),
          do: {p, r, t}

    bad_cmd_in =
      for p <- @partitions,
          r = restored.partitions[p].cmd_in,
          r not in [truth.partitions[p].cmd_in, {nil, nil}],
          do: {p, :cmd_in, r}

    letter = fn state, l ->
      Map.get(state.unknown, l, {nil, Map.get(state, :unknown_default, :none)})
    end

    bad_letters =
      for l <- @letters,
          r = letter.(restored, l),
          r != letter.(truth, l) and not match?({nil, {:no_data, _}}, r),
          do: {l, r, letter.(truth, l)}

    # the last string as it was, or unknown (never quietly none: SUN_COMM would take a resend
    # of it for a new string and run it again)
    bad_last =
      if restored.last_string in [truth.last_string, {:unknown, nil}],
        do: [],
        else: [restored.last_string]

    bad_partitions ++ bad_cmd_in ++ bad_letters ++ bad_last
  end

  # the truth as the restarted workstation must answer it: what was EXECUTING was interrupted
  defp interrupted(dump) do
    update_in(dump.partitions, fn ps ->
      Map.new(ps, fn
        {p, %{status: :executing} = e} -> {p, %{e | status: {:error, "INTERRUPTED BY RESTART"}}}
        other -> other
      end)
    end)
  end

  test "a journal damaged anywhere restores each status as it was or as unknown — through the journal process",
       %{tmp_dir: dir} do
    property =
      :proper.forall(
        tuple([resize(30, list(op())), damage(), range(2, 40)]),
        fn {ops, damage, every} ->
          reporting(fn ->
            id = "damage-#{System.unique_integer([:positive])}"
            jdir = Path.join(dir, id)
            start(id, jdir, every)
            Enum.each(ops, &run(id, &1))
            truth = Mailbox.dump(Mailbox.table(id))
            stop(id)

            path = Path.join(jdir, "journal.log")
            File.write!(path, damaged(File.read!(path), damage))
            log = ExUnit.CaptureLog.capture_log(fn -> start(id, jdir, every) end)
            restored = Mailbox.dump(Mailbox.table(id))
            stop(id)
            truth = interrupted(truth)

            bad = true_or_unknown(restored, truth)
            # loud: anything not restored as it was is logged and the file kept aside
            quiet? =
              if damage == :none,
                do: restored == truth and not (log =~ "journal of #{inspect(id)} damaged"),
                else:
                  restored == truth or
                    (log =~ "journal of #{inspect(id)} damaged at byte" and
                       Enum.any?(File.ls!(jdir), &String.starts_with?(&1, "journal.damaged-")))

            (bad == [] and quiet?) or
              tell("damage #{inspect(damage)}: wrong #{inspect(bad)}, loud: #{quiet?}\n#{log}")
          end)
        end
      )

    assert_property(property, 300)
  end

  ## The same on many more cases, without processes: the file the journal writes, damaged

  # a journal as the journal process writes it: a snapshot, records, the end mark
  defp record do
    oneof([
      tuple([exactly(:status), elements(@partitions), range(0, 9999), status(), exactly("T")]),
      tuple([exactly(:status), elements(@partitions), range(0, 9999), status()]),
      tuple([exactly(:finish), elements(@partitions), range(0, 3), status()]),
      tuple([exactly(:unknown_status), elements(@letters), range(0, 9999), status()]),
      tuple([
        exactly(:string),
        range(0, 9999),
        exactly("*LINE*"),
        list(tuple([elements(@partitions), range(0, 3)]))
      ])
    ])
  end

  # PropEr of this OTP cannot report an exception in a property (erlang:get_stacktrace/0)
  defp reporting(fun) do
    fun.()
  rescue
    e ->
      IO.puts(Exception.format(:error, e, __STACKTRACE__))
      false
  end

  defp tell(text) do
    IO.puts(text)
    false
  end

  defp fresh do
    %{
      partitions: Map.new(@partitions, &{&1, %{number: nil, status: :none, cmd_in: {nil, nil}}}),
      last_string: {nil, nil},
      unknown: %{},
      unknown_default: :none,
      leases: []
    }
  end

  test "a journal file damaged anywhere: every status true or unknown (many cases, no processes)" do
    property =
      :proper.forall(
        tuple([resize(20, list(record())), resize(20, list(record())), damage()]),
        fn {before, records, damage} ->
          reporting(fn ->
            {:ok, snapshot} =
              Enum.reduce(before, {:ok, fresh()}, fn r, {:ok, st} ->
                Replay.apply_record(r, st)
              end)

            bin =
              IO.iodata_to_binary(
                [Log.record({:snapshot, snapshot}) | Enum.map(records, &Log.record/1)] ++
                  [Log.end_mark()]
              )

            {truth, []} = Replay.replay(Log.parse(bin), fresh())
            {restored, problems} = Replay.replay(Log.parse(damaged(bin, damage)), fresh())
            bad = true_or_unknown(restored, truth)

            (bad == [] and (restored == truth or problems != [])) or
              tell(
                "damage #{inspect(damage)}: wrong #{inspect(bad)}, problems #{inspect(problems)}"
              )
          end)
        end
      )

    assert_property(property, 3_000)
  end
end
