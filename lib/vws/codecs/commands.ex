defmodule Vws.Codecs.Commands do
  @moduledoc """
  The command sets of the seed (App. I A–F; PROTOCOLS.md §1 "Command sets"), parsed into terms.

  Pure: no processes, no I/O. Each partition parses the text SUN_COMM wrote to its CMD_IN with
  `parse/2`; an unknown command gives `{:error, :unknown}` (the partition answers
  `ERROR UNKNOWN COMMAND <text>`), a known command with bad arguments gives `{:error, reason}`.

      iex> Vws.Codecs.Commands.parse(:robot, "DO MOVE MV1:TRANS(63.5,0,0,90,-90,0)")
      {:ok, {:do, :move, {:trans, "MV1", [63.5, 0.0, 0.0, 90.0, -90.0, 0.0]}}}
      iex> Vws.Codecs.Commands.parse(:gripper, "ROTATE_90")
      {:ok, {:rotate, 90}}
      iex> Vws.Codecs.Commands.parse(:monarch, "TABLE(3/1)")
      {:error, "TABLE LINES MUST BE ASCENDING"}
      iex> Vws.Codecs.Commands.parse(:vacuum, "BLOW")
      {:error, :unknown}

  ## Terms

    * robot: `:where`, `{:speed, n}`, `{:do, :move | :moves, loc}`, `{:do, :appro | :appros, loc, dist}`,
      `{:do, :depart | :departs, dist}`, `{:disable_tray, 1 | 2}`, `{:release_tray, 1 | 2}`,
      `:disable_table`, `:release_table`, `{:execute, name}`; a location `loc` is a name or
      `{:trans, name, [x, y, z, 90.0, -90.0, t]}`
    * monarch: `:cycle_start`, `:release_table`, `:status`, `:download_hp`,
      `{:download_hp, crc}` (ours, issue 24: the whole-program check), `:download_ge`,
      `{:download_ge, "NNNNNN.PRO" | "NNNNNN.GSU", :latest | version | {:force, version}}`
      (`DOWNLOAD_GE(nnnnnn.PRO/v/FORCE)`, issue 27: a draft too), `:compare_ge`,
      `{:compare_ge, "NNNNNN.PRO" | "NNNNNN.GSU"}` (the last three ours, issue 18: the library),
      `{:drip_feed, "NNNNNN.PRO", :latest | version, line}` (ours, issue 27: `DRIP_FEED(nnnnnn.PRO[/v][/Nk])`,
      a library program drip-fed from line k, 1 its first),
      `{:upload_ge, "NNNNNN.PRO" | "NNNNNN.GSU"}`, `:upload_sun`, `{:table, [line]}`,
      `{:program_select, "NNNNNN"}`, `{:program_delete, "NNNNNN.PRO" | "NNNNNN.GSU"}`
    * gripper: `:open`, `:close`, `{:rotate, 0 | 90 | 180 | 270}`
    * fixture: `:open`, `:close`, `:disable_table`, `:release_table`
    * vacuum: `:on`, `:off`; hydraulic: `:clamp_pallet`, `:release_pallet`
  """

  @type partition :: Vws.CEC.Mailbox.partition()
  @type result :: {:ok, term} | {:error, :unknown | String.t()}

  # the Monarch commands that are transfers on the WC link, carried out by SUN_COMM itself
  @transfers %{"DOWNLOAD_HP" => :download_hp, "UPLOAD_SUN" => :upload_sun}

  # Every kind of command each set has, with one text of each: what every guarantee that covers
  # "every command" walks (the interlock table, Vws.CEC.Interlock.Rules, is checked against it).
  # A parse that yields a kind missing here raises, so a new command cannot be forgotten.
  @examples %{
    robot: [
      where: "WHERE",
      speed: "SPEED 80",
      do: "DO MOVE SAFE",
      disable_tray: "DISABLE_TRAY1",
      release_tray: "RELEASE_TRAY1",
      disable_table: "DISABLE_TABLE",
      release_table: "RELEASE_TABLE",
      execute: "EXECUTE PARK"
    ],
    monarch: [
      cycle_start: "CYCLE_START",
      release_table: "RELEASE_TABLE",
      status: "STATUS",
      download_hp: "DOWNLOAD_HP",
      upload_sun: "UPLOAD_SUN",
      download_ge: "DOWNLOAD_GE",
      drip_feed: "DRIP_FEED",
      compare_ge: "COMPARE_GE",
      upload_ge: "UPLOAD_GE(000100.PRO)",
      program_select: "PROGRAM_SELECT(000100)",
      program_delete: "PROGRAM_DELETE(000100.PRO)",
      table: "TABLE(1/3)"
    ],
    gripper: [open: "OPEN", close: "CLOSE", rotate: "ROTATE_90"],
    fixture: [
      open: "OPEN",
      close: "CLOSE",
      disable_table: "DISABLE_TABLE",
      release_table: "RELEASE_TABLE"
    ],
    vacuum: [on: "ON", off: "OFF"],
    hydraulic: [clamp_pallet: "CLAMP_PALLET", release_pallet: "RELEASE_PALLET"]
  }

  @doc """
  Every kind of command of every set, with one command text of each:
  `%{partition => [{kind, text}]}`. A kind is the parsed term's atom, or its first element
  (`{:do, :move, "SAFE"}` is a `:do`).

      iex> Vws.Codecs.Commands.kinds()[:vacuum]
      [on: "ON", off: "OFF"]
  """
  @spec kinds() :: %{partition => [{atom, String.t()}]}
  def kinds, do: @examples

  @doc "Parses a command of a partition's set."
  @spec parse(partition, String.t()) :: result
  def parse(partition, text) when is_binary(text) do
    case do_parse(partition, normalise(text)) do
      {:ok, command} = ok ->
        kind = if is_tuple(command), do: elem(command, 0), else: command

        unless Keyword.has_key?(Map.get(@examples, partition, []), kind),
          do: raise(ArgumentError, "command kind #{inspect(kind)} of #{partition} not in kinds/0")

        ok

      error ->
        error
    end
  end

  @doc """
  The transfer a Monarch command's text asks SUN_COMM for, or nil for every other text.
  SUN_COMM recognises these words and nothing else: every other command is parsed once, by its
  partition.

    * `:upload_sun` — `UPLOAD_SUN`
    * `:download_hp` — `DOWNLOAD_HP`, the seed's form: no whole-program check asked
    * `{:download_hp, crc}` — `DOWNLOAD_HP(cccc)`: the WC names the program's CRC-16/ARC
      (PROTOCOLS.md §1 "Whole-program check", `Vws.Codecs.WC.ProgramCRC`)
    * `{:error, reason}` — `DOWNLOAD_HP` with an argument that is not four hex digits: still a
      download (the WC sends its lines), which ends `ERROR <reason>` and stores nothing

        iex> Vws.Codecs.Commands.transfer(" download_hp")
        :download_hp
        iex> Vws.Codecs.Commands.transfer("DOWNLOAD_HP(52D5)")
        {:download_hp, 0x52D5}
        iex> Vws.Codecs.Commands.transfer("DOWNLOAD_HP(52D)")
        {:error, "BAD PROGRAM CRC 52D"}
        iex> Vws.Codecs.Commands.transfer("TABLE(1/2)")
        nil
  """
  @spec transfer(String.t()) ::
          :download_hp | {:download_hp, 0..0xFFFF} | :upload_sun | {:error, String.t()} | nil
  def transfer(text) when is_binary(text) do
    case normalise(text) do
      "DOWNLOAD_HP" <> arg when arg != "" -> download_crc(arg)
      text -> Map.get(@transfers, text)
    end
  end

  # `(cccc)`, the program's CRC named by the WC; a text that is not parenthesised is another
  # word (`DOWNLOAD_HPX`), not a transfer
  defp download_crc(arg) do
    case parenthesised(arg) do
      {:ok, hex} ->
        case Vws.Codecs.WC.ProgramCRC.parse(hex) do
          {:ok, crc} -> {:download_hp, crc}
          :error -> {:error, bad_crc(hex)}
        end

      {:error, :unknown} ->
        nil
    end
  end

  # SUN_COMM shows it to the WC as it is: words, whatever the WC wrote (Vws.Codecs.WC.Words)
  defp bad_crc(""), do: "BAD PROGRAM CRC"
  defp bad_crc(hex), do: "BAD PROGRAM CRC " <> Vws.Codecs.WC.Words.of(hex)

  defp normalise(text), do: text |> String.trim() |> String.upcase()

  # Robot (App. I B)
  defp do_parse(:robot, "WHERE"), do: {:ok, :where}
  defp do_parse(:robot, "DISABLE_TABLE"), do: {:ok, :disable_table}
  defp do_parse(:robot, "RELEASE_TABLE"), do: {:ok, :release_table}

  defp do_parse(:robot, "DISABLE_TRAY" <> n) when n in ["1", "2"],
    do: {:ok, {:disable_tray, String.to_integer(n)}}

  defp do_parse(:robot, "RELEASE_TRAY" <> n) when n in ["1", "2"],
    do: {:ok, {:release_tray, String.to_integer(n)}}

  defp do_parse(:robot, "SPEED " <> n) do
    case number(n) do
      {:ok, v} when v > 0 -> {:ok, {:speed, v}}
      _ -> {:error, "BAD SPEED #{String.trim(n)}"}
    end
  end

  defp do_parse(:robot, "EXECUTE " <> name) do
    name = String.trim(name)

    if name =~ ~r/^[A-Z][A-Z0-9_.]{0,14}$/,
      do: {:ok, {:execute, name}},
      else: {:error, "BAD PROGRAM NAME #{name}"}
  end

  defp do_parse(:robot, "DO " <> instruction), do: robot_do(String.trim_leading(instruction))

  # Monarch (App. I A)
  defp do_parse(:monarch, "CYCLE_START"), do: {:ok, :cycle_start}
  defp do_parse(:monarch, "RELEASE_TABLE"), do: {:ok, :release_table}
  defp do_parse(:monarch, "STATUS"), do: {:ok, :status}

  defp do_parse(:monarch, text) when is_map_key(@transfers, text),
    do: {:ok, Map.fetch!(@transfers, text)}

  # ours (issue 24): the WC names the program's CRC
  defp do_parse(:monarch, "DOWNLOAD_HP" <> _ = text) do
    case transfer(text) do
      {:download_hp, crc} -> {:ok, {:download_hp, crc}}
      {:error, _} = error -> error
      nil -> {:error, :unknown}
    end
  end

  defp do_parse(:monarch, "DOWNLOAD_GE"), do: {:ok, :download_ge}
  defp do_parse(:monarch, "DRIP_FEED"), do: {:ok, :drip_feed}

  # ours (issue 18): a program of the library, its latest version or version v
  defp do_parse(:monarch, "DOWNLOAD_GE" <> arg) do
    with {:ok, inner} <- parenthesised(arg) do
      case String.split(inner, "/") do
        [file] ->
          with {:ok, file} <- program_file(file), do: {:ok, {:download_ge, file, :latest}}

        [file, v] ->
          with {:ok, file} <- program_file(file),
               {:ok, n} <- version(v),
               do: {:ok, {:download_ge, file, n}}

        # ours (issue 27): a version sent whatever its workflow state, draft included
        [file, v, "FORCE"] ->
          with {:ok, file} <- program_file(file),
               {:ok, n} <- version(v),
               do: {:ok, {:download_ge, file, {:force, n}}}

        _ ->
          {:error, "BAD PROGRAM FILE #{inner}"}
      end
    end
  end

  # ours (issue 27): a program of the library drip-fed, its latest released version or version
  # v, from its first line or restarted at line k (`/Nk`, the modal state restored)
  defp do_parse(:monarch, "DRIP_FEED" <> arg) do
    with {:ok, inner} <- parenthesised(arg) do
      case String.split(inner, "/") do
        [file | rest] when length(rest) <= 2 ->
          with {:ok, file} <- program_file(file),
               :ok <-
                 if(String.ends_with?(file, ".PRO"),
                   do: :ok,
                   else: {:error, "BAD PROGRAM FILE #{file}"}
                 ),
               {:ok, which, line} <- drip_from(rest) do
            {:ok, {:drip_feed, file, which, line}}
          end

        _ ->
          {:error, "BAD PROGRAM FILE #{inner}"}
      end
    end
  end

  defp do_parse(:monarch, "COMPARE_GE"), do: {:ok, :compare_ge}

  defp do_parse(:monarch, "COMPARE_GE" <> arg) do
    with {:ok, file} <- parenthesised(arg),
         {:ok, file} <- program_file(file),
         do: {:ok, {:compare_ge, file}}
  end

  defp do_parse(:monarch, "UPLOAD_GE" <> arg) do
    with {:ok, file} <- parenthesised(arg),
         {:ok, file} <- program_file(file),
         do: {:ok, {:upload_ge, file}}
  end

  defp do_parse(:monarch, "PROGRAM_DELETE" <> arg) do
    with {:ok, file} <- parenthesised(arg),
         {:ok, file} <- program_file(file),
         do: {:ok, {:program_delete, file}}
  end

  defp do_parse(:monarch, "PROGRAM_SELECT" <> arg) do
    with {:ok, n} <- parenthesised(arg) do
      if n =~ ~r/^\d{6}$/,
        do: {:ok, {:program_select, n}},
        else: {:error, "BAD PROGRAM NUMBER #{n}"}
    end
  end

  defp do_parse(:monarch, "TABLE" <> arg) do
    with {:ok, list} <- parenthesised(arg) do
      lines = String.split(list, "/")

      cond do
        not Enum.all?(lines, &(&1 =~ ~r/^\d{1,3}$/)) -> {:error, "BAD TABLE LINES #{list}"}
        length(lines) > 8 -> {:error, "AT MOST 8 TABLE LINES"}
        true -> ascending(Enum.map(lines, &String.to_integer/1))
      end
    end
  end

  # Gripper (App. I D), fixture (E), vacuum (C), hydraulic (F)
  defp do_parse(:gripper, "OPEN"), do: {:ok, :open}
  defp do_parse(:gripper, "CLOSE"), do: {:ok, :close}

  defp do_parse(:gripper, "ROTATE_" <> n) when n in ["0", "90", "180", "270"],
    do: {:ok, {:rotate, String.to_integer(n)}}

  defp do_parse(:fixture, "OPEN"), do: {:ok, :open}
  defp do_parse(:fixture, "CLOSE"), do: {:ok, :close}
  defp do_parse(:fixture, "DISABLE_TABLE"), do: {:ok, :disable_table}
  defp do_parse(:fixture, "RELEASE_TABLE"), do: {:ok, :release_table}
  defp do_parse(:vacuum, "ON"), do: {:ok, :on}
  defp do_parse(:vacuum, "OFF"), do: {:ok, :off}
  defp do_parse(:hydraulic, "CLAMP_PALLET"), do: {:ok, :clamp_pallet}
  defp do_parse(:hydraulic, "RELEASE_PALLET"), do: {:ok, :release_pallet}
  defp do_parse(_partition, _text), do: {:error, :unknown}

  defp robot_do("MOVES " <> loc), do: with({:ok, l} <- location(loc), do: {:ok, {:do, :moves, l}})
  defp robot_do("MOVE " <> loc), do: with({:ok, l} <- location(loc), do: {:ok, {:do, :move, l}})
  defp robot_do("APPROS " <> arg), do: appro(:appros, arg)
  defp robot_do("APPRO " <> arg), do: appro(:appro, arg)
  defp robot_do("DEPARTS " <> d), do: depart(:departs, d)
  defp robot_do("DEPART " <> d), do: depart(:depart, d)
  defp robot_do(_), do: {:error, :unknown}

  defp appro(kind, arg) do
    case String.split(arg, "/", parts: 2) do
      [loc, dist] ->
        with {:ok, l} <- location(loc), {:ok, d} <- distance(dist), do: {:ok, {:do, kind, l, d}}

      _ ->
        {:error, "APPRO NEEDS LOCATION/DISTANCE"}
    end
  end

  defp depart(kind, d), do: with({:ok, d} <- distance(d), do: {:ok, {:do, kind, d}})

  defp distance(text) do
    case number(text) do
      {:ok, d} -> {:ok, d}
      :error -> {:error, "BAD DISTANCE #{String.trim(text)}"}
    end
  end

  # `MV1` or `MV1:TRANS(x/y/z/90/-90/t)` (`,` accepted for `/`, blanks ignored)
  defp location(text) do
    text = String.replace(text, " ", "")

    case Regex.run(~r/^([A-Z][A-Z0-9_.]{0,14})(?::TRANS\(([^()]*)\))?$/, text) do
      [_, name] ->
        {:ok, name}

      [_, name, args] ->
        values = args |> String.split(["/", ","]) |> Enum.map(&number/1)

        if length(values) == 6 and Enum.all?(values, &match?({:ok, _}, &1)) do
          {:ok, {:trans, name, Enum.map(values, fn {:ok, v} -> v * 1.0 end)}}
        else
          {:error, "BAD TRANS #{args}"}
        end

      nil ->
        {:error, "BAD LOCATION #{text}"}
    end
  end

  defp number(text) do
    text = String.trim(text)

    case Float.parse(text) do
      {v, ""} -> {:ok, v}
      _ -> :error
    end
  end

  defp drip_from([]), do: {:ok, :latest, 1}
  defp drip_from(["N" <> k]), do: with({:ok, k} <- restart_line(k), do: {:ok, :latest, k})
  defp drip_from([v]), do: with({:ok, n} <- version(v), do: {:ok, n, 1})

  defp drip_from([v, "N" <> k]) do
    with {:ok, n} <- version(v), {:ok, k} <- restart_line(k), do: {:ok, n, k}
  end

  defp drip_from([v, other]) do
    with {:ok, _n} <- version(v),
         do: {:error, bad("BAD RESTART LINE ", other)}
  end

  defp version(v) do
    case Integer.parse(v) do
      {n, ""} when n in 1..999_999 -> {:ok, n}
      _ -> {:error, bad("BAD VERSION ", v)}
    end
  end

  # what the WC wrote, in words (an ERROR text, PROTOCOLS.md §1)
  defp bad(what, ""), do: String.trim(what)
  defp bad(what, text), do: what <> Vws.Codecs.WC.Words.of(text)

  defp restart_line(k) do
    case Integer.parse(k) do
      {n, ""} when n in 1..9_999_999 -> {:ok, n}
      _ -> {:error, bad("BAD RESTART LINE N", k)}
    end
  end

  defp parenthesised(arg) do
    case Regex.run(~r/^\s*\(\s*([^()]*?)\s*\)\s*$/, arg) do
      [_, inner] -> {:ok, inner}
      nil -> {:error, :unknown}
    end
  end

  defp program_file(file) do
    if file =~ ~r/^\d{6}\.(PRO|GSU)$/, do: {:ok, file}, else: {:error, "BAD PROGRAM FILE #{file}"}
  end

  defp ascending(lines) do
    if lines == Enum.sort(Enum.uniq(lines)),
      do: {:ok, {:table, lines}},
      else: {:error, "TABLE LINES MUST BE ASCENDING"}
  end
end
