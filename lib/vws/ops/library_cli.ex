defmodule Vws.Ops.LibraryCLI do
  @moduledoc """
  The program library on the command line (`mix vws.library`; `bin/vws-library` in a release,
  with the same options): works on the library's directory
  itself, so on a running workstation's library as well as on a stopped one's (`Vws.CEC.Library`
  keeps stores from several OS processes apart).

      mix vws.library list                          # every program, its latest version, on the machine
      mix vws.library show 001234.PRO               # its versions
      mix vws.library show 001234.PRO --version 2   # version 2's text
      mix vws.library import part.nc                # a new version (named by its O word)
      mix vws.library import part.nc --name 1234
      mix vws.library export 001234.PRO out.nc [--version 2]
      mix vws.library diff 001234.PRO 1 2           # version 1 against 2 (2 omitted: the latest)
      mix vws.library release 001234.PRO 3          # version 3 (from the machine) as the latest released
      mix vws.library compare                       # each program: same / differs / absent
      mix vws.library compare --refresh --endpoint tcp://127.0.0.1:7070

  Which library: `--library DIR`, else `library/<id>` of the data directory (`--id`, default
  `$VWS_ID`, else `VWS`; `$VWS_LIBRARY_DIR`, `$VWS_DATA_DIR` as for `mix vws.serve`: `Vws.Ops.DataDir`).

  `compare` shows the machine's directory as MONARCH last read it (after every DOWNLOAD_GE, on
  `COMPARE_GE`), with the time it was read; `--refresh` first has the running workstation read
  it again, as its WC: it sends the Monarch command `COMPARE_GE` to `--endpoint` (default
  `tcp://127.0.0.1:7070`; `Vws.Peers.WC.CLI`).

  `import` takes only an NC program (`Vws.CEC.Library.check_program/1`: `%` first and
  last, the O word after the first `%`, text, at most 64 MiB, `Vws.CEC.Library.max_bytes/0`;
  a program over 999,999 bytes is kept for drip feeds, but never stored on the GE-2000) and says why it refuses
  anything else (`tool.py: not an NC program: its first line is not %`, exit status 1); a file
  holding exactly the latest version is not stored again (`same as 001234.PRO v2, nothing
  stored`, exit status 0).

  Exit status: 0 done; 1 not found, not stored, or different (`diff` of two different versions
  exits 0); 2 a usage error.
  """

  alias Vws.CEC.Library
  alias Vws.Ops.LibraryText

  @switches [
    id: :string,
    library: :string,
    version: :pos_integer,
    name: :string,
    source: :string,
    refresh: :boolean,
    endpoint: :string,
    machine: :boolean,
    cached: :boolean,
    draft: :boolean,
    comment: :string,
    why: :string,
    in: :string,
    limit: :pos_integer,
    help: :boolean
  ]

  @doc "Runs the command line `argv`, printing to standard output; returns the exit status."
  @spec main([String.t()]) :: 0 | 1 | 2
  def main(argv) do
    # the flags' errors in words, as every VWS command says them (Vws.CLIOptions)
    case Vws.CLIOptions.parse(argv, @switches) do
      {:ok, opts, args} ->
        if opts[:help] do
          IO.puts(usage())
          0
        else
          id = opts[:id] || System.get_env("VWS_ID") || "VWS"
          lib = {:dir, opts[:library] || Vws.Ops.DataDir.library_dir(id, :default)}
          run(args, opts, lib)
        end

      {:error, line} ->
        usage_error(line)
    end
  end

  @doc false
  # For the release's bin/vws-library (bin/vws eval takes no arguments: they come as
  # VWS_CLI_ARG_<i> environment variables, VWS_CLI_ARGC of them); halts with the exit status.
  def release_main do
    argc = String.to_integer(System.get_env("VWS_CLI_ARGC", "0"))
    argv = for i <- 0..(argc - 1)//1, do: System.get_env("VWS_CLI_ARG_#{i}", "")
    System.halt(main(argv))
  end

  defp run(["list"], _opts, lib), do: print_compare(lib)

  defp run(["show", name], opts, lib) do
    case opts[:version] do
      nil ->
        with {:ok, versions} <- Library.versions(lib, name),
             {:ok, result} <- Library.compare(lib) do
          row = Enum.find(result.programs, &(&1.name == hd(versions).name))
          latest = row.latest && row.latest.version
          IO.puts("#{row.name}: #{length(versions)} versions")

          for v <- versions do
            marks =
              [
                row.on_machine == {:same, v.version} && "on the machine",
                v.version == latest && "latest released",
                not v.released && Library.release_text(v)
              ]
              |> Enum.filter(& &1)

            mark = if marks == [], do: "", else: "  <- " <> Enum.join(marks, ", ")
            IO.puts("  v#{v.version}  #{line(v)}#{mark}")
            if v[:comment], do: IO.puts("        comment: #{v.comment}")
          end

          {:ok, tombstones} = Library.tombstones(lib, row.name)

          for t <- tombstones do
            last = List.last(t.changes)
            IO.puts("  v#{t.version}  deleted #{last.at} by #{last.by} (#{last.what})")
          end

          IO.puts(
            "on the machine: #{LibraryText.on_machine_text(row.on_machine, latest, versions)}"
          )

          0
        end

      n ->
        with {:ok, bytes, v} <- Library.read(lib, name, n) do
          IO.puts("#{v.name} v#{v.version}  #{line(v)}")
          IO.write(bytes)
          0
        end
    end
    |> result(name)
  end

  defp run(["import", path], opts, lib) do
    store_opts =
      [source: opts[:source] || "cli"] ++
        if(opts[:name], do: [name: opts[:name]], else: []) ++
        if(opts[:draft], do: [state: :draft], else: []) ++
        if(opts[:comment], do: [comment: opts[:comment]], else: [])

    case Library.import_file(lib, path, store_opts) do
      {:ok, v} ->
        IO.puts("stored #{v.name} v#{v.version}  #{line(v)}")
        0

      {:same, v} ->
        IO.puts("#{path}: same as #{v.name} v#{v.version}, nothing stored")
        0

      error ->
        result(error, path)
    end
  end

  defp run(["export", name, path], opts, lib) do
    case Library.export(lib, name, opts[:version] || :latest, path) do
      {:ok, v} ->
        IO.puts("#{v.name} v#{v.version} written to #{path} (#{v.size} bytes)")
        0

      error ->
        result(error, name)
    end
  end

  # the library's version against what the machine holds, read back (COMPARE_GE as its WC)
  defp run(["diff", name], opts, lib) do
    if opts[:machine],
      do: diff_machine(name, opts, lib),
      else: usage_error("diff NAME needs V1 [V2], or --machine")
  end

  defp run(["diff", name, a | b], _opts, lib) when length(b) <= 1 do
    with {:ok, a} <- version_arg(a),
         {:ok, b} <- version_arg(List.first(b, "latest")),
         {:ok, diff} <- Library.diff(lib, name, a, b) do
      case LibraryText.format_diff(diff) do
        [] -> IO.puts("#{name}: v#{a} and #{b} are the same")
        lines -> Enum.each(lines, &IO.puts/1)
      end

      0
    end
    |> result(name)
  end

  defp run(["release", name, which], opts, lib) do
    with {:ok, n} <- version_arg(which),
         before = Library.version(lib, name, :latest),
         {:ok, v} <- Library.release(lib, name, n, source: opts[:source] || "cli") do
      if before == {:ok, v},
        do: IO.puts("#{v.name}: v#{v.version}, the latest released, already holds these bytes"),
        else: IO.puts("released #{v.name} as v#{v.version}  #{line(v)}")

      0
    end
    |> result(name)
  end

  defp run(["unrelease", name, which], opts, lib) do
    with {:ok, n} <- version_arg(which),
         {:ok, v} <- Library.unrelease(lib, name, n, source: opts[:source] || "cli") do
      IO.puts("#{v.name} v#{v.version} is a draft: DOWNLOAD_GE(#{v.name}) no longer sends it")
      0
    end
    |> result(name)
  end

  defp run(["comment", name, which | words], opts, lib) when words != [] do
    with {:ok, n} <- version_arg(which),
         {:ok, v} <-
           Library.comment(lib, name, n, Enum.join(words, " "), source: opts[:source] || "cli") do
      IO.puts("#{v.name} v#{v.version}: #{v.comment}")
      0
    end
    |> result(name)
  end

  defp run(["delete", name, which], opts, lib) do
    with {:ok, n} <- version_arg(which),
         {:ok, t} <-
           Library.delete(lib, name, n, source: opts[:source] || "cli", why: opts[:why]) do
      IO.puts("deleted #{t.name} v#{t.version} (its tombstone and the history keep it)")
      0
    end
    |> result(name)
  end

  defp run(["search" | words], opts, lib) when words != [] do
    where =
      case opts[:in] do
        nil -> [:name, :comment, :text]
        list -> list |> String.split(",", trim: true) |> Enum.map(&search_field/1)
      end

    with true <- Enum.all?(where, &is_atom/1) || {:error, {:bad_field, opts[:in]}},
         {:ok, hits} <- Library.search(lib, Enum.join(words, " "), in: where) do
      for h <- hits do
        IO.puts(
          "#{h.name} v#{h.version}  (#{Enum.join(h.matched, ", ")})" <>
            if(h.line, do: "  #{h.line}", else: "")
        )
      end

      if hits == [], do: 1, else: 0
    end
    |> result("search")
  end

  defp run(["history" | name], opts, lib) when length(name) <= 1 do
    with {:ok, h} <- Library.history(lib, program: List.first(name), limit: opts[:limit]) do
      lines = LibraryText.format_history(h)
      if lines == [], do: IO.puts("no transfers recorded"), else: Enum.each(lines, &IO.puts/1)
      0
    end
    |> result(List.first(name, "history"))
  end

  defp run(["compare"], opts, lib) do
    if opts[:refresh] do
      status = wc(opts, "M COMPARE_GE", [])
      if status == 0, do: print_compare(lib), else: status
    else
      print_compare(lib)
    end
  end

  defp run(args, _opts, _lib), do: usage_error("unknown command #{Enum.join(args, " ")}")

  # the library's version against what the machine holds, read back (COMPARE_GE as its WC)
  # (the WC's answer is printed by Vws.Peers.WC.CLI: DONE when the machine holds a version,
  # ERROR PROGRAM DIFFERS … with the read-back kept, or an ERROR that read nothing back)
  defp diff_machine(name, opts, lib) do
    asked_at = System.os_time(:second)

    # the WC's command names the file as the library does (1234 → 001234.PRO)
    refreshed =
      case {opts[:cached], Library.name(name)} do
        {true, _} -> 0
        {_, {:ok, file}} -> wc(opts, "M COMPARE_GE(#{file})", [])
        {_, error} -> error
      end

    case refreshed do
      status when status in [0, 1] ->
        with {:ok, which} <- version_arg(to_string(opts[:version] || "latest")),
             {:ok, d} <- Library.diff_machine(lib, name, which),
             true <-
               opts[:cached] || DateTime.to_unix(d.read_at) >= asked_at || {:error, :not_read_now} do
          v = d.version
          read = DateTime.to_iso8601(d.read_at)

          case LibraryText.format_diff(d.diff) do
            [] ->
              IO.puts("#{v.name}: the machine holds v#{v.version} exactly (read back #{read})")

            lines ->
              IO.puts(
                "--- #{v.name} v#{v.version} (library)\n+++ #{v.name} on the machine (read back #{read})"
              )

              Enum.each(lines, &IO.puts/1)
          end

          0
        end
        |> result(name)

      {:error, _} = error ->
        result(error, name)

      status ->
        status
    end
  end

  # one command as the WC (Vws.Peers.WC.CLI): its exit status, 0 DONE, 1 ERROR (printed)
  defp wc(opts, command, _extra) do
    endpoint = opts[:endpoint] || "tcp://127.0.0.1:7070"
    Vws.Peers.WC.CLI.main(["--endpoint", endpoint, "--command", command, "--quiet"])
  end

  defp search_field("name"), do: :name
  defp search_field("comment"), do: :comment
  defp search_field("text"), do: :text
  defp search_field(other), do: other

  defp print_compare(lib) do
    case Library.compare(lib) do
      {:ok, result} ->
        LibraryText.print_compare(result)
        0

      error ->
        result(error, "library")
    end
  end

  defp version_arg("latest"), do: {:ok, :latest}

  defp version_arg(text) do
    case Integer.parse(String.trim_leading(text, "v")) do
      {n, ""} when n > 0 -> {:ok, n}
      _ -> {:error, {:bad_version, text}}
    end
  end

  defp line(v) do
    crc = String.pad_leading(Integer.to_string(v.crc, 16), 4, "0")
    sha = if v.digest, do: String.slice(v.digest, 0, 16), else: "unreadable"

    "#{DateTime.to_iso8601(v.at)}  #{v.source}  #{v.size} bytes  CRC #{crc}  SHA-256 #{sha}…"
  end

  defp result(status, _what) when is_integer(status), do: status

  defp result({:error, {:bad_version, text}}, _what), do: usage_error("bad version #{text}")

  defp result({:error, {:bad_field, text}}, _what),
    do: usage_error("--in #{text}: name, comment, text")

  defp result({:error, reason}, what) do
    IO.puts(:stderr, "#{what}: #{reason_text(reason)}")
    1
  end

  defp reason_text(:not_found), do: "not in the library"
  defp reason_text(:bad_name), do: "not a program name (nnnnnn.PRO or nnnnnn.GSU)"
  defp reason_text(:damaged), do: "its file is damaged (size, CRC or SHA-256 not as stored)"
  defp reason_text(:not_released), do: "no released version (every one came from the machine)"
  defp reason_text(:no_program_number), do: "no program number (O word); give --name"

  defp reason_text(:too_large),
    do: "larger than #{Library.max_bytes()} bytes, the most the library keeps"

  defp reason_text(:enoent), do: "no such file"
  defp reason_text(:deleted), do: "that version was deleted (its tombstone: show)"

  defp reason_text(:not_read_back),
    do: "the machine's copy was never read back (COMPARE_GE, or diff --machine without --cached)"

  defp reason_text(:not_read_now),
    do: "nothing was read back from the machine (the WC's answer above says why)"

  defp reason_text(:bad_comment), do: "a comment is at most 200 printable characters"
  defp reason_text({:not_a_program, why}), do: LibraryText.program_refusal(why)
  defp reason_text({:not_a_file, type}), do: "not a regular file (#{type})"
  defp reason_text(reason), do: inspect(reason)

  defp usage_error(message) do
    IO.puts(:stderr, "mix vws.library: #{message}\n\n" <> usage())
    2
  end

  defp usage do
    """
    usage: mix vws.library [--id ID | --library DIR] COMMAND
      list
      show NAME [--version V]
      import FILE [--name NAME] [--source SOURCE] [--draft] [--comment TEXT]
      export NAME FILE [--version V]
      diff NAME V1 [V2]
      release NAME V [--source SOURCE]
      unrelease NAME V
      comment NAME V TEXT…
      delete NAME V [--why TEXT]
      search TEXT… [--in name,comment,text]
      history [NAME] [--limit N]
      diff --machine NAME [--version V] [--endpoint tcp://127.0.0.1:7070] [--cached]
      compare [--refresh [--endpoint tcp://127.0.0.1:7070]]\
    """
  end
end
