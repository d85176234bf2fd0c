defmodule Vws.CEC.Journal.Replay do
  @moduledoc """
  What the journal's records restore: a fold of the records over the restorable state, that
  never fails and never restores an older status as the current one.

  The state is `Vws.CEC.Mailbox.dump/1`'s with the interlock's `:leases`. Every record the live
  system writes is applied here (`apply_record/2`); the journal applies each record as it writes
  it too, so its snapshots are exactly what replaying the records they replace would give.

  ## What cannot be applied

  A record is checked before it is applied: its frame's checksums (`Vws.CEC.Journal.Log`), then
  that it decodes (only a frame whose CRC-32s hold is decoded), then its shape — every field of
  the kind and range the live system writes; a partition, status or tag this version does not
  know is refused. What fails is a *problem*
  `{offset, why}`, and everything the lost bytes could have changed is marked unknown from that
  point: a command status reads `NO DATA (JOURNAL DAMAGED)` (the bytes are no frame: damaged,
  cut short, the end mark missing) or `NO DATA (JOURNAL RECORD UNREADABLE)` (a whole frame whose
  record cannot be applied: undecodable, a shape or a kind this version does not know). A status
  record or finish that names its partition marks only that partition; anything else marks every
  command status, the statuses of unknown set letters (those never seen too) and the last
  string. A record after the damage that writes a status whole (a dispatch, a status, a string's
  commands, a snapshot) makes it known again; a finish does not (it applies only to the number
  the status showed, which is unknown).

  Leases cannot be marked unknown: the ones held before the damage are kept (the safe side: a
  volume stays held) and the problem is reported; a lease taken in the lost bytes is not known.
  """

  alias Vws.CEC.Mailbox

  @damaged "JOURNAL DAMAGED"
  @unreadable "JOURNAL RECORD UNREADABLE"

  @type state :: map
  @type problem :: {non_neg_integer, String.t()}

  @doc "The words for damaged bytes and for an unreadable record."
  def damaged, do: @damaged
  def unreadable, do: @unreadable

  @doc """
  Replays the items of `Vws.CEC.Journal.Log.parse/1` over `state`: `{state, problems}`, the
  problems in file order, each `{offset, words}`.
  """
  @spec replay([Vws.CEC.Journal.Log.item()], state) :: {state, [problem]}
  def replay(items, state) do
    {state, problems} =
      Enum.reduce(items, {normalize(state), []}, fn item, {st, problems} ->
        case item(item) do
          {:ok, record} ->
            case apply_record(record, st) do
              {:ok, st} ->
                {st, problems}

              {:error, why, scope} ->
                {mark(st, scope, @unreadable), [{elem(item, 1), why} | problems]}

              {:partly, st, why, scope} ->
                {mark(st, scope, @unreadable), [{elem(item, 1), why} | problems]}
            end

          {:damaged, off, why} ->
            {mark(st, :all, @damaged), [{off, why} | problems]}

          {:unreadable, off, why} ->
            {mark(st, :all, @unreadable), [{off, why} | problems]}
        end
      end)

    {state, Enum.reverse(problems)}
  end

  # Decoded only once both CRC-32s of its frame hold: bytes this journal wrote. Not with `:safe`:
  # the atoms of work volumes and lease reasons (`:tray1`, `:inside`) exist only once the modules
  # naming them are loaded, which at the start they may not be yet (a restarted node), and
  # `:safe` refused them — the leases of a robot inside the vise were lost. The shape check
  # below refuses what this version does not know.
  defp item({:record, off, payload}) do
    {:ok, :erlang.binary_to_term(payload)}
  rescue
    ArgumentError -> {:unreadable, off, "RECORD NOT DECODABLE (WRITTEN BY A NEWER VERSION?)"}
  end

  defp item({:term, _off, term}), do: {:ok, term}

  defp item({:kind, off, kind}),
    do: {:unreadable, off, "FRAME OF UNKNOWN KIND #{kind} (WRITTEN BY A NEWER VERSION?)"}

  defp item({:damaged, off, {:unreadable_file, why}}),
    do: {:damaged, off, "FILE UNREADABLE (#{String.upcase(why)})"}

  defp item({:damaged, off, why}) when is_binary(why), do: {:damaged, off, why}

  defp item({:damaged, off, :bad_header}), do: {:damaged, off, "DAMAGED BYTES (NO FRAME)"}
  defp item({:damaged, off, :bad_checksum}), do: {:damaged, off, "RECORD CHECKSUM WRONG"}
  defp item({:damaged, off, :cut_short}), do: {:damaged, off, "LAST RECORD CUT SHORT"}

  defp item({:damaged, off, :no_end_mark}),
    do: {:damaged, off, "NO END MARK (CUT SHORT OR ITS END DAMAGED)"}

  @doc """
  Applies one record: `{:ok, state}`, `{:error, words, scope}` when it cannot be applied
  (`scope`: `{:partition, p}`, `{:letter, l}`, a list of those or `:all`: what it could have
  changed), or `{:partly, state, words, scope}` (a snapshot with entries this version cannot read).
  """
  @spec apply_record(term, state) ::
          {:ok, state} | {:error, String.t(), term} | {:partly, state, String.t(), term}
  def apply_record({:snapshot, snapshot}, state) when is_map(snapshot),
    do: apply_snapshot(snapshot, state)

  # SUN_COMM before 2026-11 journaled the rule-2 error of a status command (set S, which has no
  # status location) as a status: there is nothing to restore from it
  def apply_record({tag, :status, n, status}, state)
      when tag in [:status, :finish] and is_integer(n) do
    if status?(status), do: {:ok, state}, else: {:error, "RECORD OF UNKNOWN SHAPE", :all}
  end

  def apply_record({:status, p, n, status, text}, state) do
    if partition?(p) and number?(n) and status?(status) and is_binary(text),
      do: {:ok, put_entry(state, p, %{number: n, status: status, cmd_in: {n, text}})},
      else: {:error, shape_words(p), scope(p)}
  end

  def apply_record({:status, p, n, status}, state) do
    if partition?(p) and number?(n) and status?(status) do
      entry = state.partitions[p]
      {:ok, put_entry(state, p, %{entry | number: n, status: status})}
    else
      {:error, shape_words(p), scope(p)}
    end
  end

  def apply_record({:finish, p, n, status}, state) do
    if partition?(p) and number?(n) and status?(status) do
      case state.partitions[p] do
        %{number: ^n} = entry -> {:ok, put_entry(state, p, %{entry | status: status})}
        _other -> {:ok, state}
      end
    else
      {:error, shape_words(p), scope(p)}
    end
  end

  def apply_record({:unknown_status, letter, n, status}, state) do
    if letter?(letter) and number?(n) and status?(status),
      do: {:ok, %{state | unknown: Map.put(state.unknown, letter, {n, status})}},
      else:
        {:error, "RECORD OF UNKNOWN SHAPE",
         if(letter?(letter), do: {:letter, letter}, else: :all)}
  end

  def apply_record({:string, seq, line, commands}, state) do
    if number?(seq) and is_binary(line) and is_list(commands) and
         Enum.all?(
           commands,
           &match?({p, n} when is_atom(p) and is_integer(n) and n in 0..9999, &1)
         ) and
         Enum.all?(commands, fn {p, _} -> partition?(p) end) do
      # acknowledged: until a later record says otherwise, each command counts as under way
      state =
        Enum.reduce(commands, %{state | last_string: {seq, line}}, fn {p, n}, st ->
          put_entry(st, p, %{st.partitions[p] | number: n, status: :executing})
        end)

      {:ok, state}
    else
      {:error, "RECORD OF UNKNOWN SHAPE", :all}
    end
  end

  # a lease keeps its place among the others (the earliest first) while it is held
  def apply_record({:lease, volume, holder, reasons}, state)
      when is_atom(volume) and is_atom(holder) and is_list(reasons) do
    if Enum.all?(reasons, &is_atom/1) do
      {:ok, %{state | leases: lease(state.leases, volume, holder, reasons)}}
    else
      {:error, "RECORD OF UNKNOWN SHAPE", :all}
    end
  end

  def apply_record(_other, _state), do: {:error, "RECORD OF UNKNOWN SHAPE", :all}

  defp shape_words(p) do
    if is_atom(p) and not partition?(p),
      do:
        "RECORD NAMES NO PARTITION OF THIS VERSION (#{p |> Atom.to_string() |> String.upcase()})",
      else: "RECORD OF UNKNOWN SHAPE"
  end

  defp scope(p), do: if(partition?(p), do: {:partition, p}, else: :all)

  defp lease(leases, volume, holder, reasons) do
    held? = &match?({^volume, ^holder, _}, &1)

    cond do
      reasons == [] ->
        Enum.reject(leases, held?)

      Enum.any?(leases, held?) ->
        Enum.map(leases, &if(held?.(&1), do: {volume, holder, reasons}, else: &1))

      true ->
        leases ++ [{volume, holder, reasons}]
    end
  end

  # A snapshot is the whole state: what it holds of a partition, letter or lease is checked
  # entry by entry; a partition it lacks or holds in another shape is unknown.
  defp apply_snapshot(snap, state) do
    partitions = Map.get(snap, :partitions)
    last = Map.get(snap, :last_string, {nil, nil})
    unknown = Map.get(snap, :unknown, %{})
    default = Map.get(snap, :unknown_default, :none)
    leases = Map.get(snap, :leases, [])

    if is_map(partitions) and is_map(unknown) and is_list(leases) and status?(default) and
         last_string?(last) and Enum.all?(leases, &lease?/1) do
      {ps, missing} =
        Enum.reduce(Mailbox.partitions(), {%{}, []}, fn p, {ps, missing} ->
          case Map.get(partitions, p) do
            %{number: n, status: st, cmd_in: {in_n, text}} = e
            when (is_nil(n) or is_integer(n)) and (is_nil(in_n) or is_integer(in_n)) and
                   (is_nil(text) or is_binary(text)) ->
              if status?(st) and (n == nil or number?(n)),
                do: {Map.put(ps, p, Map.take(e, [:number, :status, :cmd_in])), missing},
                else: {Map.put(ps, p, unknown_entry(@unreadable)), [p | missing]}

            _ ->
              {Map.put(ps, p, unknown_entry(@unreadable)), [p | missing]}
          end
        end)

      letters =
        for {l, {n, st}} <- unknown,
            letter?(l),
            n == nil or number?(n),
            status?(st),
            into: %{},
            do: {l, {n, st}}

      dropped = for {l, _} <- unknown, not Map.has_key?(letters, l), do: l

      state = %{
        state
        | partitions: ps,
          last_string: last,
          unknown: letters,
          unknown_default: default,
          leases: leases
      }

      cond do
        missing == [] and dropped == [] ->
          {:ok, state}

        Enum.all?(dropped, &letter?/1) ->
          scope = Enum.map(missing, &{:partition, &1}) ++ Enum.map(dropped, &{:letter, &1})
          {:partly, state, "SNAPSHOT PARTLY UNREADABLE", scope}

        true ->
          {:partly, state, "SNAPSHOT PARTLY UNREADABLE", :all}
      end
    else
      {:error, "SNAPSHOT OF UNKNOWN SHAPE", :all}
    end
  end

  @doc "`state` with what `scope` covers marked unknown (`why`: the words in `NO DATA (…)`)."
  @spec mark(state, term, String.t()) :: state
  def mark(state, {:partition, p}, why), do: put_entry(state, p, unknown_entry(why))

  def mark(state, scopes, why) when is_list(scopes),
    do: Enum.reduce(scopes, state, &mark(&2, &1, why))

  def mark(state, {:letter, l}, why),
    do: %{state | unknown: Map.put(state.unknown, l, {nil, {:no_data, why}})}

  def mark(state, :all, why) do
    %{
      state
      | partitions: Map.new(state.partitions, fn {p, _} -> {p, unknown_entry(why)} end),
        # the last string may be in what was lost: unknown, not absent (SUN_COMM then runs
        # nothing of the first string it gets, which may be that one again — rule 4 cannot tell)
        last_string: {:unknown, nil},
        unknown: Map.new(state.unknown, fn {l, _} -> {l, {nil, {:no_data, why}}} end),
        unknown_default: {:no_data, why}
    }
  end

  defp unknown_entry(why), do: %{number: nil, status: {:no_data, why}, cmd_in: {nil, nil}}

  defp put_entry(state, p, entry), do: %{state | partitions: Map.put(state.partitions, p, entry)}

  @doc "The state with every key this version expects (a dump of an older table lacks some)."
  @spec normalize(map) :: state
  def normalize(state) do
    state
    |> Map.put_new(:leases, [])
    |> Map.put_new(:unknown, %{})
    |> Map.put_new(:unknown_default, :none)
  end

  @doc "A status of the shape the mailbox holds."
  def status?(s) when s in [:none, :executing, :done], do: true
  def status?({:error, why}) when is_binary(why), do: true
  def status?({:no_data, why}) when is_binary(why), do: true
  def status?(_), do: false

  defp partition?(p), do: p in Mailbox.partitions()
  defp number?(n), do: is_integer(n) and n in 0..9999
  defp letter?(l), do: is_binary(l) and byte_size(l) in 1..4

  defp last_string?({nil, nil}), do: true
  defp last_string?({:unknown, nil}), do: true
  defp last_string?({seq, line}), do: number?(seq) and is_binary(line)
  defp last_string?(_), do: false

  defp lease?({v, h, r}),
    do: is_atom(v) and is_atom(h) and is_list(r) and Enum.all?(r, &is_atom/1)

  defp lease?(_), do: false
end
