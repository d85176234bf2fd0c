defmodule Vws.CEC.SunComm.SessionTest do
  # SUN_COMM's pure core without processes, sockets or a workstation: the WC's lines cross an
  # in-memory line that flips bits (into CR and LF too), cuts lines short, loses and repeats
  # them; the requests the core makes are answered by a model of the mailboxes and the journal
  # (which may refuse); the transfer timers fire when the script says so.
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.CEC.SunComm.Session
  alias Vws.Codecs.WC.{BCC, Command, CommandString, LineDecoder, ProgramCRC, Reply, Words}

  doctest Session

  @ctx %{now: 0}
  @requests [:journal, :dispatch, :claim, :read_status, :read_nc_up, :store_program]

  ## The model around the core

  # The mailboxes and the journal as the core sees them through its requests.
  defp env(opts \\ []) do
    %{
      journal: :ok,
      store: :ok,
      in_flight: %{},
      claimed: nil,
      last_string: {nil, nil},
      nc_up: Keyword.get(opts, :nc_up, []),
      stored: [],
      finished: []
    }
  end

  # Carries out one result of the core on the model: replies and effects in order, a request
  # answered and its answer given back at once. `out` lists everything in order:
  # `{:reply, r}`, `{:effect, e}`, `{:request, r, answer}`.
  defp carry({s, replies, effects}, env, out) do
    out = out ++ Enum.map(replies, &{:reply, &1})
    {plain, requests} = Enum.split_with(effects, &(not request?(&1)))

    # a request is the last effect, or there is none
    assert requests == [] or [List.last(effects)] == requests

    env = Enum.reduce(plain, env, &apply_effect/2)
    out = out ++ Enum.map(plain, &{:effect, &1})

    case requests do
      [] ->
        {s, env, out}

      [request] ->
        {env, answer} = answer(request, env)
        carry(Session.handle_result(s, answer, @ctx), env, out ++ [{:request, request, answer}])
    end
  end

  defp request?(effect), do: elem(effect, 0) in @requests

  defp answer({:journal, _record}, env), do: {env, env.journal}
  defp answer({:read_status, _name}, env), do: {env, "0000NONE"}
  defp answer({:read_nc_up}, env), do: {env, env.nc_up}

  defp answer({:store_program, lines}, env),
    do: {%{env | stored: env.stored ++ [{lines, env.store}]}, env.store}

  defp answer({how, set, n, _text}, env) when how in [:dispatch, :claim] do
    case env.in_flight do
      %{^set => busy} ->
        {env, {:busy, busy}}

      _ ->
        env = %{env | in_flight: Map.put(env.in_flight, set, n)}
        {if(how == :claim, do: %{env | claimed: n}, else: env), :ok}
    end
  end

  defp apply_effect({:remember_string, seq, line}, env), do: %{env | last_string: {seq, line}}

  defp apply_effect({:finish, n, status}, env) do
    # only the transfer's own command ends, once, while it is in flight
    assert env.claimed == n and env.in_flight[:monarch] == n
    assert status == :done or match?({:error, _}, status)

    %{
      env
      | in_flight: Map.delete(env.in_flight, :monarch),
        claimed: nil,
        finished: env.finished ++ [{n, status}]
    }
  end

  defp apply_effect(_effect, env), do: env

  # Partitions finish what they were given (not the transfer SUN_COMM carries out).
  defp partitions_idle(%{claimed: nil} = env), do: %{env | in_flight: %{}}
  defp partitions_idle(env), do: %{env | in_flight: Map.take(env.in_flight, [:monarch])}

  # Feeds bytes as the server does: cut into lines by the line decoder; what is left unfinished
  # is dropped by the partial-line timer. Returns what each line (or dropped tail) gave:
  # `[{line | :unfinished, mode before, out, last string before}]`.
  defp feed(s, env, bytes) do
    {lines, dec} = LineDecoder.feed(LineDecoder.new(), bytes)
    lines = if LineDecoder.buffered(dec) > 0, do: lines ++ [:unfinished], else: lines

    Enum.reduce(lines, {s, env, []}, fn line, {s, env, fed} ->
      before = {Session.mode(s), env.last_string}

      result =
        if line == :unfinished,
          do: Session.unfinished_line(s),
          else: Session.handle_line(s, line, @ctx)

      {s, env, out} = carry(result, env, [])
      {s, env, fed ++ [{line, elem(before, 0), out, elem(before, 1)}]}
    end)
  end

  defp replies(out), do: for({:reply, r} <- out, do: r)

  defp answers(out),
    do: Enum.filter(replies(out), &(&1 == :nak or elem(&1, 0) in [:ack, :status, :line_ack]))

  defp wc_string(seq, commands),
    do:
      %CommandString{
        sequence: seq,
        commands: Enum.map(commands, fn {l, n, t} -> Command.new(l, n, t) end)
      }
      |> CommandString.encode()
      |> IO.iodata_to_binary()

  defp program_line(n, text), do: IO.iodata_to_binary(Reply.encode({:line, rem(n, 10_000), text}))

  ## The line's faults

  defp fault do
    :proper_types.frequency([
      {6, :intact},
      {1, :lost},
      {1, :again},
      {1, :answer_lost},
      {2, {:flip, :proper_types.range(0, 200), :proper_types.range(0, 7)}},
      {1, {:crlf, :proper_types.range(0, 200), :proper_types.oneof([?\r, ?\n])}},
      {1, {:cut, :proper_types.range(0, 200)}}
    ])
  end

  # the bytes of `line` (CR LF included) as the line delivers them
  defp damage(_bytes, :lost), do: ""
  defp damage(bytes, :again), do: bytes <> bytes

  defp damage(bytes, {:flip, pos, bit}) do
    pos = rem(pos, byte_size(bytes) - 2)
    <<head::binary-size(pos), byte, tail::binary>> = bytes
    <<head::binary, Bitwise.bxor(byte, Bitwise.bsl(1, bit)), tail::binary>>
  end

  defp damage(bytes, {:flip_no_break, pos, bit}) do
    damaged = damage(bytes, {:flip, pos, bit})

    if String.contains?(binary_part(damaged, 0, byte_size(damaged) - 2), ["\r", "\n"]),
      do: bytes,
      else: damaged
  end

  defp damage(bytes, {:crlf, pos, byte}) do
    pos = rem(pos, byte_size(bytes) - 2)
    <<head::binary-size(pos), _, tail::binary>> = bytes
    <<head::binary, byte, tail::binary>>
  end

  defp damage(bytes, {:cut, len}), do: binary_part(bytes, 0, rem(len, byte_size(bytes) - 1))
  defp damage(bytes, _intact), do: bytes

  # the same damage, except a CR or LF inside the line
  defp no_line_break({:crlf, _, _}), do: :intact
  defp no_line_break({:flip, pos, bit}), do: {:flip_no_break, pos, bit}
  defp no_line_break(fault), do: fault

  ## Command strings

  defp command do
    :proper_types.tuple([
      :proper_types.elements(~w(R G F V H M S A Q)),
      :proper_types.range(0, 9),
      :proper_types.elements([
        "WHERE",
        "OPEN",
        "CLOSE",
        "ON",
        "ROBOT_CMD",
        "DOWNLOAD_HP",
        "UPLOAD_SUN",
        "X-J*"
      ])
    ])
  end

  defp string_step do
    :proper_types.tuple([
      :proper_types.range(0, 4),
      :proper_types.non_empty(:proper_types.resize(3, :proper_types.list(command()))),
      fault(),
      :proper_types.frequency([{5, :ok}, {1, {:error, :disk_full}}]),
      :proper_types.boolean()
    ])
  end

  # commands that could not be sent at all (a `*` in the text) are left out
  defp sendable({_letter, _n, text}), do: not String.contains?(text, "*")

  test "every line from the WC gets exactly one answer; nothing runs unless journaled first" do
    property =
      :proper.forall(:proper_types.resize(40, :proper_types.list(string_step())), fn steps ->
        Enum.reduce(steps, {Session.new(), env()}, fn {seq, commands, fault, journal, idle},
                                                      {s, env} ->
          commands = Enum.filter(commands, &sendable/1)
          commands = if commands == [], do: [{"R", 1, "WHERE"}], else: commands
          line = wc_string(seq, commands)
          {s, env, fed} = feed(s, %{env | journal: journal}, damage(line, fault))

          for {fed_line, mode, out, before} <- fed, mode != :upload do
            # exactly one A/E/status answer to each line
            assert length(answers(out)) == 1, inspect({fed_line, mode, out})
            check_order(fed_line, before, out)
          end

          {s, if(idle, do: partitions_idle(env), else: env)}
        end)

        true
      end)

    assert_property(property, 300)
  end

  # Journal before acknowledgement, acknowledgement and remembering before dispatch; a string
  # that is not journaled (or not intact) runs nothing; every ERROR in words.
  defp check_order(line, before, out) do
    journaled =
      Enum.find_index(out, &match?({:request, {:journal, {:string, _, ^line, _}}, :ok}, &1))

    for {{:request, {how, set, n, _}, _}, i} <- Enum.with_index(out),
        how in [:dispatch, :claim] do
      assert journaled != nil and journaled < i
      {:request, {:journal, {:string, seq, ^line, commands}}, :ok} = Enum.at(out, journaled)
      assert {set, n} in commands
      assert Enum.find_index(out, &(&1 == {:effect, {:remember_string, seq, line}})) < i
      assert Enum.find_index(out, &(&1 == {:reply, {:ack, seq}})) < i
    end

    # acknowledged: journaled now, or the very string acknowledged last (a resend)
    for {:reply, {:ack, seq}} <- out, do: assert(journaled != nil or before == {seq, line})

    for {:effect, {tag, _, _, {:error, words}}} <- out,
        tag == :status,
        do: assert(Words.text?(words))

    for {:effect, {:finish, _, {:error, words}}} <- out, do: assert(Words.text?(words))
  end

  test "a string not journaled is answered E and nothing in it runs; sent again, it runs" do
    line = wc_string(7, [{"R", 3, "WHERE"}]) |> String.trim_trailing()
    env = %{env() | journal: {:error, :disk_full}}
    {s, env, out} = carry(Session.handle_line(Session.new(), line, @ctx), env, [])
    assert replies(out) == [:nak]
    refute Enum.any?(out, &match?({:request, {:dispatch, _, _, _}, _}, &1))

    {_s, _env, out} = carry(Session.handle_line(s, line, @ctx), %{env | journal: :ok}, [])
    assert replies(out) == [{:ack, 7}]
    assert {:request, {:dispatch, :robot, 3, "WHERE"}, :ok} in out
  end

  test "a resent string (same number, same bytes) is acknowledged again and runs nothing" do
    line = wc_string(8, [{"G", 4, "OPEN"}]) |> String.trim_trailing()
    {s, env, _} = carry(Session.handle_line(Session.new(), line, @ctx), env(), [])
    {_s, _env, out} = carry(Session.handle_line(s, line, @ctx), env, [])
    assert replies(out) == [{:ack, 8}]
    refute Enum.any?(out, &match?({:request, _, _}, &1))
  end

  test "after a damaged journal (last string unknown) the first command string runs nothing; " <>
         "status queries are answered; the next string runs" do
    s = Session.new(last_string: {:unknown, nil})
    env = env()

    # a status query first: answered, and the first command string is still the one denied
    status = wc_string(20, [{"S", 1, "ROBOT_CMD"}]) |> String.trim_trailing()
    {s, env, out} = carry(Session.handle_line(s, status, @ctx), env, [])
    assert [{:status, 1, "0000NONE"}] = replies(out)

    # it may be the lost string again: acknowledged, journaled, nothing dispatched, each command
    # answers why in words
    line = wc_string(21, [{"R", 7, "DO MOVE MV1"}, {"G", 8, "OPEN"}]) |> String.trim_trailing()
    {s, env, out} = carry(Session.handle_line(s, line, @ctx), env, [])
    assert replies(out) == [{:ack, 21}]
    assert Enum.any?(out, &match?({:request, {:journal, {:string, 21, _, _}}, :ok}, &1))

    refute Enum.any?(
             out,
             &match?({:request, {how, _, _, _}, _} when how in [:dispatch, :claim], &1)
           )

    for {set, n} <- [robot: 7, gripper: 8] do
      assert {:effect, {:status, ^set, ^n, {:error, words}}} =
               Enum.find(out, &match?({:effect, {:status, ^set, ^n, _}}, &1))

      assert words =~ "NOT RUN" and Words.text?(words)
    end

    # sent again (its acknowledgement lost): rule 4 knows it now, nothing runs
    {s, env, out} = carry(Session.handle_line(s, line, @ctx), env, [])
    assert replies(out) == [{:ack, 21}]
    refute Enum.any?(out, &match?({:request, _, _}, &1))

    # the WC sends them under a new number: they run
    again = wc_string(22, [{"R", 9, "DO MOVE MV1"}]) |> String.trim_trailing()
    {_s, _env, out} = carry(Session.handle_line(s, again, @ctx), env, [])
    assert replies(out) == [{:ack, 22}]
    assert {:request, {:dispatch, :robot, 9, "DO MOVE MV1"}, :ok} in out
  end

  test "a command for a busy set answers ERROR BUSY and does not run; the others of its string do" do
    line = wc_string(9, [{"G", 5, "OPEN"}, {"R", 6, "WHERE"}]) |> String.trim_trailing()
    env = %{env() | in_flight: %{gripper: 4}}
    {_s, _env, out} = carry(Session.handle_line(Session.new(), line, @ctx), env, [])
    assert {:effect, {:status, :gripper, 5, {:error, "BUSY 0004"}}} in out
    assert {:request, {:dispatch, :robot, 6, "WHERE"}, :ok} in out
  end

  ## DOWNLOAD_HP

  defp program do
    text = :proper_types.list(:proper_types.elements(~c"GX01.5 -JM*N%"))

    :proper_types.bind(
      :proper_types.resize(12, :proper_types.list(text)),
      fn texts ->
        body = for t <- texts, t = List.to_string(t), String.trim(t) != "%", do: t
        :proper_types.exactly(["%", "O1234" | body] ++ ["%"])
      end,
      false
    )
  end

  # DOWNLOAD_HP 0001 acknowledged, naming the program's CRC or not: the session in download mode
  defp start_download(program, crc?) do
    command =
      if crc?,
        do: "DOWNLOAD_HP(#{ProgramCRC.format(ProgramCRC.compute(program))})",
        else: "DOWNLOAD_HP"

    line = wc_string(1, [{"M", 1, command}]) |> String.trim_trailing()
    {s, env, _} = carry(Session.handle_line(Session.new(), line, @ctx), env(), [])
    assert Session.mode(s) == :download
    {s, env}
  end

  # The WC sends the program line after line; it goes on to the next line when its line was
  # answered A with its number, else sends it again. A step may let the download's timer fire.
  defp download(program, faults, crc?) do
    # without a named CRC only damage that does not break the line in two
    faults = if crc?, do: faults, else: Enum.map(faults, &no_line_break/1)

    {s, env} = start_download(program, crc?)

    {s, env, _next} =
      Enum.reduce_while(faults, {s, env, 1}, fn fault, {s, env, next} ->
        cond do
          Session.mode(s) != :download or next > length(program) ->
            {:halt, {s, env, next}}

          fault == :stall ->
            {s, env, _} = carry(Session.handle_timeout(s, :no_line, @ctx), env, [])
            {:halt, {s, env, next}}

          fault == :skip ->
            # a WC that gives up on a line and goes on without its answer
            {:cont, {s, env, next + 1}}

          true ->
            bytes = program_line(next, Enum.at(program, next - 1))
            {s, env, fed} = feed(s, env, damage(bytes, fault))

            for {_line, :download, out, _} <- fed, do: assert(length(answers(out)) == 1)

            answered? =
              fault != :answer_lost and
                Enum.any?(fed, fn {_, _, out, _} ->
                  Enum.any?(replies(out), &match?({:line_ack, n} when n == rem(next, 10_000), &1)) or
                    Enum.any?(
                      replies(out),
                      &match?({:line_ack, n, _} when n == rem(next, 10_000), &1)
                    )
                end)

            {:cont, {s, env, if(answered?, do: next + 1, else: next)}}
        end
      end)

    # a transfer cut off: the link goes
    {_s, env, _} = carry(Session.link_lost(s, "WC LINK LOST"), env, [])
    env
  end

  defp download_faults,
    do:
      :proper_types.resize(
        60,
        :proper_types.list(:proper_types.frequency([{30, fault()}, {1, :stall}, {1, :skip}]))
      )

  defp check_download(program, env) do
    # the command ends once; it ends DONE only when this very program was stored
    assert [{1, status}] = env.finished

    for {lines, _answer} <- env.stored, do: assert(lines == program)

    if status == :done, do: assert(env.stored == [{program, :ok}])
    true
  end

  test "a damaged download (bit flips into CR and LF too, cut lines, losses, a skipped line, a stall, a cut-off) " <>
         "with the program's CRC named never stores other bytes, and ends once" do
    property =
      :proper.forall({program(), download_faults()}, fn {program, faults} ->
        check_download(program, download(program, faults, true))
      end)

    assert_property(property, 300)
  end

  test "without a named CRC, lines damaged anywhere but into CR or LF never store other bytes" do
    property =
      :proper.forall({program(), download_faults()}, fn {program, faults} ->
        check_download(program, download(program, faults, false))
      end)

    assert_property(property, 300)
  end

  test "a protocol limit, pinned: without a named CRC, an LF damaged into a line whose head " <>
         "carries a valid BCC stores the head (the BCC is the link's only check); with the CRC, ERROR" do
    head = "0002G1 X"
    text = "G1 X" <> BCC.encode(BCC.compute(head)) <> "5.0"
    program = ["%", text, "%"]
    damaged = program_line(2, text) |> damage({:crlf, byte_size(head) + 3, ?\n})

    for {crc?, expected} <- [{false, :done}, {true, :error}] do
      {s, env} = start_download(program, crc?)
      {s, env, _} = feed(s, env, program_line(1, "%"))
      {s, env, fed} = feed(s, env, damaged)
      assert [{_, _, head_out, _}, {_, _, tail_out, _}] = fed
      assert replies(head_out) == [{:line_ack, 2}] and replies(tail_out) == [:nak]
      {_s, env, _} = feed(s, env, program_line(3, "%"))

      case {expected, env.finished} do
        {:done, [{1, :done}]} -> assert env.stored == [{["%", "G1 X", "%"], :ok}]
        {:error, [{1, {:error, "PROGRAM CRC " <> _}}]} -> assert env.stored == []
      end
    end
  end

  ## UPLOAD_SUN

  # The WC takes line after line: it keeps a line whose number is the next, answers it A with
  # its number, answers A again to the line it has; its answers cross the lossy line.
  defp upload(program, faults) do
    line = wc_string(2, [{"M", 2, "UPLOAD_SUN"}]) |> String.trim_trailing()

    {s, env, out} =
      carry(
        Session.handle_line(Session.new(upload_retries: 3), line, @ctx),
        env(nc_up: program),
        []
      )

    assert Session.mode(s) == :upload

    {s, env, wc, _} =
      Enum.reduce_while(faults, {s, env, [], replies(out)}, fn fault, {s, env, wc, inbox} ->
        if Session.mode(s) != :upload do
          {:halt, {s, env, wc, inbox}}
        else
          {wc, answer} = wc_takes(wc, inbox)

          {s, env, out} =
            case answer && damage(answer, fault) do
              nil -> carry(Session.handle_timeout(s, :no_answer, @ctx), env, [])
              "" -> carry(Session.handle_timeout(s, :no_answer, @ctx), env, [])
              bytes -> feed_all(s, env, bytes)
            end

          sent = for {:line, n, _} <- replies(out), do: n
          # a line goes only once the one before it was taken, never ahead
          assert Enum.all?(sent, &(&1 in [length(wc), length(wc) + 1]))
          {:cont, {s, env, wc, replies(out)}}
        end
      end)

    {_s, env, _} = carry(Session.link_lost(s, "WC LINK LOST"), env, [])
    {env, Enum.reverse(wc)}
  end

  defp feed_all(s, env, bytes) do
    {s, env, fed} = feed(s, env, bytes)
    {s, env, Enum.flat_map(fed, fn {_, _, out, _} -> out end)}
  end

  # `wc`: the lines taken, newest first. The WC answers the last program line of its inbox.
  defp wc_takes(wc, inbox) do
    case for({:line, n, text} <- inbox, do: {n, text}) |> List.last() do
      nil ->
        {wc, nil}

      {n, text} ->
        wc = if n == length(wc) + 1, do: [text | wc], else: wc

        if n == length(wc),
          do: {wc, IO.iodata_to_binary(Reply.encode({:line_ack, n}))},
          else: {wc, "E\r\n"}
    end
  end

  test "a damaged upload ends once, and DONE only when the WC took every line, in order, intact" do
    property =
      :proper.forall({program(), download_faults()}, fn {program, faults} ->
        faults = Enum.map(faults, &if(&1 in [:stall, :skip], do: :lost, else: &1))
        {env, wc} = upload(program, faults)
        assert [{2, status}] = env.finished

        if status == :done do
          assert {:ok, "%", crc} = ProgramCRC.split_closing(List.last(wc))
          assert Enum.drop(wc, -1) ++ ["%"] == program and crc == ProgramCRC.compute(program)
        end

        true
      end)

    assert_property(property, 300)
  end
end
