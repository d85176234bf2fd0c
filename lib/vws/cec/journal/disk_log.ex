defmodule Vws.CEC.Journal.DiskLog do
  @moduledoc """
  Reads, once, a journal of the `disk_log` wrap format that earlier versions wrote (`journal.1`,
  `journal.idx`, `journal.siz`, … in the journal directory), for `Vws.CEC.Journal` to restore.

  Its records carry no checksum of their own, so a damaged record may still decode; what
  `disk_log` cannot read (a torn or damaged record, a file that is no log) becomes a `:damaged`
  item, and the replay marks what it could have changed unknown. The old files are moved aside
  into `journal.disk_log-<UTC time>/` first and read from a copy (reading repairs it).
  """

  require Logger

  @doc """
  `:none` when the directory holds no such journal, else `{:ok, items, aside}`: the items for
  `Vws.CEC.Journal.Replay.replay/2` (`{:term, index, record}` and `{:damaged, index, words}`)
  and the directory the old files were moved to.
  """
  @spec read(Path.t()) :: :none | {:ok, list, Path.t()}
  def read(dir) do
    case Path.wildcard(Path.join(dir, "journal.{idx,siz,[0-9]*}")) do
      [] ->
        :none

      files ->
        stamp = Calendar.strftime(DateTime.utc_now(), "%Y%m%dT%H%M%S%fZ")
        aside = Path.join(dir, "journal.disk_log-" <> stamp)
        work = Path.join(dir, "journal.disk_log-reading")
        File.rm_rf!(work)
        File.mkdir_p!(aside)
        File.mkdir_p!(work)

        for f <- files do
          File.rename!(f, Path.join(aside, Path.basename(f)))
          File.cp!(Path.join(aside, Path.basename(f)), Path.join(work, Path.basename(f)))
        end

        Logger.warning("journal of the disk_log format found: read once, moved to #{aside}")
        items = read_log(Path.join(work, "journal"))
        File.rm_rf(work)
        {:ok, items, aside}
    end
  end

  defp read_log(file) do
    name = {:vws_journal_migration, make_ref()}

    opened =
      try do
        :disk_log.open(
          name: name,
          file: String.to_charlist(file),
          type: :wrap,
          repair: true,
          mode: :read_write
        )
      catch
        kind, reason -> {:error, {kind, reason}}
      end

    case opened do
      {:ok, ^name} ->
        read_all(name)

      {:repaired, ^name, _recovered, {:badbytes, bad}} ->
        items = read_all(name)

        if bad > 0,
          do: items ++ [{:damaged, length(items), "#{bad} TORN BYTES DROPPED"}],
          else: items

      {:error, reason} ->
        Logger.error("journal of the disk_log format cannot be opened: #{inspect(reason)}")
        [{:damaged, 0, "OLD JOURNAL CANNOT BE OPENED"}]

      other ->
        Logger.error("journal of the disk_log format cannot be opened: #{inspect(other)}")
        [{:damaged, 0, "OLD JOURNAL CANNOT BE OPENED"}]
    end
  end

  defp read_all(name) do
    items = read_all(name, :start, 0, [])
    :disk_log.close(name)
    items
  end

  defp read_all(name, cont, i, acc) do
    case safe_chunk(name, cont) do
      :eof ->
        Enum.reverse(acc)

      {:error, _reason} ->
        Enum.reverse([{:damaged, i, "OLD JOURNAL UNREADABLE FROM HERE"} | acc])

      {cont, terms} ->
        read_all(name, cont, i + length(terms), terms(terms, i, acc))

      {cont, terms, bad} ->
        acc = terms(terms, i, acc)
        i = i + length(terms)
        read_all(name, cont, i + 1, [{:damaged, i, "#{bad} DAMAGED BYTES"} | acc])
    end
  end

  defp terms(terms, i, acc) do
    terms
    |> Enum.with_index(i)
    |> Enum.reduce(acc, fn {t, j}, acc -> [{:term, j, t} | acc] end)
  end

  defp safe_chunk(name, cont) do
    :disk_log.chunk(name, cont, 1)
  catch
    kind, reason -> {:error, {kind, reason}}
  end
end
