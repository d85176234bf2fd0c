defmodule Vws.Ops.Web.State do
  @moduledoc """
  What the dashboard shows, as JSON-ready data (`Vws.Ops.Web.JSON`). For every workstation of the node
  (`Vws.CEC.Workstation.list/0`), all read through `Vws.Ops.Inspect`:

    * `partitions` — state, command, status (and its class: `done`, `executing`, `error`,
      `none`), the command running and for how long, counts, restarts, the link it uses;
    * `devices` — the device-status locations as the WC reads them, with their age;
    * `sensors` — the numbers behind them: every quantity of DAQ #1's latest poll (jaw width,
      finger gap, vise strain gauge, …, `Vws.Links.DAQ.Readings.quantities/1`) and the clamp forces of
      the hydraulic controller's latest `PALLET?` answer, each `%{key, name, value, unit}`, and
      the switches in words;
    * `interlocks` — the leases: volume, holder, reasons, age;
    * `links` — every device link: its name, state, counters, retries, last error, details;
    * `wc` — the WC link (state, peer, mode, counters, retransmissions) and its recent dialogue;
    * `transfers` — NC transfers under way (DOWNLOAD_HP/UPLOAD_SUN on the WC link,
      DOWNLOAD_GE/UPLOAD_GE on the DNC link): lines or blocks and bytes so far and in all,
      rate, ETA;
    * `library` — the program library (`Vws.CEC.Library`, issue 18), nil without one: how many
      programs and versions, when the machine's directory was last read, how many programs are
      the same / differ / are absent on the machine, and the 30 programs stored last with
      their latest version and where they stand on the machine;
    * `restart` — the last drip feed restarted at a line (issue 27), nil if none since the node
      started: `%{time, program, version, line, preamble}`, the preamble being the lines that
      restore the modal state, told before the first block went (`Vws.Ops.Web.History.restart/1`);
    * `alerts` — what is wrong now: commands ended in error, devices without data, links down
      or with a last error.

  Besides: `equipment` — the hydraulic controller(s) running on this node outside any
  workstation, with their link to DAQ #2 (`Vws.Ops.Inspect.equipment_rows/0`); `cell` — when the
  node is connected to others, every workstation of the cell with its node and state
  (`Vws.CEC.Cell.workstations/1`), else nil.

  Every value is text or a number the way a person reads it (`"0007"`, `"ERROR NO LINK TO VAL
  II"`, `"NO DATA (NO LINK TO DAQ #1)"`): never an Elixir term. A part that cannot be read is
  shown as such; it never empties the rest.
  """

  alias Vws.Ops.Inspect
  alias Vws.CEC.Mailbox

  @dialogue_lines 40
  # link states that mean the link cannot be used now
  @bad_states ~w(down not_answering unreadable restarting disconnected connecting halted)

  @doc """
  Now, as the state's `time` says it (ISO 8601, UTC, milliseconds): a command's answer says when
  it was taken the same way, so that the page can tell a state read before it (string order).
  """
  @spec time() :: String.t()
  def time, do: DateTime.utc_now() |> DateTime.truncate(:millisecond) |> DateTime.to_iso8601()

  @doc """
  The dashboard state. Options: `:control` (whether control actions are enabled),
  `:library_cache` (a public ETS table: the library section is then read again only when older
  than ten times what reading it took, see `library/2`), `:workstations` (the ids of the
  workstations to show; default every workstation of this node).
  """
  @spec build(keyword) :: map
  def build(opts \\ []) do
    ids = Keyword.get_lazy(opts, :workstations, &Vws.CEC.Workstation.list/0)
    cache = Keyword.get(opts, :library_cache)

    %{
      time: time(),
      node: to_string(node()),
      control: Keyword.get(opts, :control, false),
      cell: cell(),
      equipment: equipment(),
      workstations:
        ids
        |> Task.async_stream(&workstation(&1, cache), timeout: 10_000, on_timeout: :kill_task)
        |> Enum.zip(ids)
        |> Enum.flat_map(fn
          {{:ok, shown}, _ws} -> shown
          {{:exit, reason}, ws} -> [unreadable(ws, reason)]
        end)
    }
  end

  defp cell do
    if Node.list() != [] do
      for w <- Vws.CEC.Cell.workstations(2_000) do
        %{
          id: label(w.id),
          node: to_string(w.node),
          state: Inspect.words(w.state),
          wc: w |> Map.get(:wc) |> then(&(&1 && Inspect.words(&1))),
          wc_connected: Map.get(w, :wc_connected, false),
          in_flight:
            for {p, {n, :executing}} <- Map.get(w, :commands, %{}) do
              "#{String.upcase(to_string(p))} #{number(n)}"
            end
        }
      end
    end
  end

  defp equipment do
    for e <- Inspect.equipment_rows() do
      info = e.info || %{}

      %{
        name: e.name,
        state: Inspect.words(e.state),
        status: info |> Map.get(:status) |> status_text(),
        details:
          info
          |> Map.drop([:phase, :status])
          |> Enum.sort()
          |> Enum.map_join(", ", fn {k, v} -> "#{Inspect.words(k)} #{Inspect.words(v)}" end),
        links: Enum.map(e.links, &link/1)
      }
    end
  rescue
    # the registry went away (the node is stopping), or a controller stopped while read
    e ->
      [
        %{
          name: "equipment",
          state: "could not be read: #{Inspect.words(e)}",
          status: nil,
          details: "",
          links: []
        }
      ]
  end

  defp status_text(nil), do: nil
  defp status_text(:done), do: "DONE"
  defp status_text(:executing), do: "EXECUTING"
  defp status_text(:none), do: "NONE"
  defp status_text({:error, why}) when is_binary(why), do: "ERROR " <> why
  defp status_text(other), do: Inspect.words(other)

  # A workstation whose state could not be read at all is still listed, saying so.
  defp unreadable(ws, reason) do
    %{
      id: label(ws),
      unreadable: "could not be read: #{Inspect.words(reason)}",
      partitions: [],
      devices: [],
      sensors: %{poll: nil, age_ms: nil, note: nil, quantities: [], switches: []},
      interlocks: [],
      links: [],
      wc: wc(%{info: :not_answering, dialogue: []}),
      transfers: [],
      library: nil,
      alerts: [%{where: label(ws), text: "could not be read", severity: "error"}],
      last_sequence: nil,
      events: [],
      history: Vws.Ops.Web.History.recent(ws),
      restart: Vws.Ops.Web.History.restart(ws)
    }
  end

  defp workstation(ws, cache) do
    if Mailbox.exists?(ws), do: [workstation!(ws, cache)], else: []
  rescue
    # stopped while we read it: not shown; still there: shown, saying it could not be read
    e -> if Mailbox.exists?(ws), do: [unreadable(ws, e)], else: []
  end

  defp workstation!(ws, cache) do
    snapshot = Inspect.snapshot(ws)
    now = System.monotonic_time(:millisecond)
    partitions = Enum.map(snapshot.partitions, &partition/1)
    devices = devices(snapshot.mailboxes.devices)
    links = Enum.map(snapshot.links, &link/1)
    wc = wc(snapshot.wc)
    sensors = sensors(snapshot.mailboxes.devices, Mailbox.readings(ws))

    %{
      id: label(ws),
      partitions: partitions,
      devices: devices,
      sensors: sensors,
      interlocks:
        for i <- snapshot.interlocks do
          %{
            what: Inspect.label(i.what),
            holder: if(i.holder == nil, do: "-", else: Inspect.label(i.holder)),
            reasons: Enum.map_join(i.reasons, ", ", &Inspect.words/1),
            age_ms: i.age_ms
          }
        end,
      links: links,
      wc: wc,
      transfers: transfers(snapshot, now),
      library: library(ws, cache),
      alerts: alerts(partitions, devices, links, wc, sensors),
      last_sequence: number(snapshot.mailboxes.last_sequence),
      events: for({e, n} <- snapshot.mailboxes.events, do: %{event: Inspect.words(e), count: n}),
      history: Vws.Ops.Web.History.recent(ws),
      restart: Vws.Ops.Web.History.restart(ws)
    }
  end

  @library_rows 30

  @doc false
  # The library's summary and its programs stored last. All of it is read (bench/library.exs has
  # what that costs with 10,000 programs: a few hundred ms), so with a cache it is read again only
  # when older than ten times what the last reading took: a small library at every build, one of
  # 10,000 programs every few seconds — at most a tenth of the time on it, whatever the size.
  def library(lib, nil), do: library(lib)

  def library(lib, cache) do
    now = System.monotonic_time(:millisecond)

    case :ets.lookup(cache, {:library, lib}) do
      [{_, shown, at, took}] when now - at < 10 * took ->
        shown

      _ ->
        shown = library(lib)
        took = System.monotonic_time(:millisecond) - now
        :ets.insert(cache, {{:library, lib}, shown, now, took})
        shown
    end
  end

  @doc false
  def library(lib) do
    with true <- Vws.CEC.Library.enabled?(lib),
         {:ok, c} <- Vws.CEC.Library.compare(lib) do
      words = fn p ->
        Vws.Ops.LibraryText.on_machine_text(
          p.on_machine,
          p.latest && p.latest.version,
          p.versions
        )
      end

      # the latest released version, else (every version from the machine) the newest
      shown = fn p -> p.latest || p.newest end

      %{
        programs: length(c.programs),
        versions: Enum.reduce(c.programs, 0, &(length(&1.versions) + &2)),
        read_at: c.read_at && DateTime.to_iso8601(c.read_at),
        machine_only: c.machine_only,
        counts: Enum.frequencies_by(c.programs, &on_machine_class(&1.on_machine)),
        rows:
          c.programs
          |> Enum.sort_by(&DateTime.to_unix(&1.newest.at, :millisecond), :desc)
          |> Enum.take(@library_rows)
          |> Enum.map(fn p ->
            v = shown.(p)

            newer =
              for u <- p.versions,
                  not u.released,
                  p.latest == nil or u.version > p.latest.version,
                  do: u

            unreleased = Enum.map(newer, &"v#{&1.version}")
            not_released = Vws.Ops.LibraryText.not_released_text(newer)

            %{
              name: p.name,
              versions: length(p.versions),
              latest: v.version,
              # versions the operator sent from the machine, and drafts: not released
              note:
                cond do
                  p.latest == nil ->
                    not_released

                  unreleased != [] ->
                    "#{Enum.join(unreleased, ", ")} #{not_released}"

                  true ->
                    ""
                end,
              at: DateTime.to_iso8601(v.at),
              source: v.source,
              size: v.size,
              crc: String.pad_leading(Integer.to_string(v.crc, 16), 4, "0"),
              on_machine: words.(p),
              on_machine_class: on_machine_class(p.on_machine)
            }
          end),
        history: transfer_history(lib)
      }
    else
      false -> nil
      {:error, reason} -> %{error: "could not be read: #{Inspect.words(reason)}"}
    end
  end

  @history_rows 10

  # the newest transfers of the library's history (issue 27), and the damaged parts skipped
  defp transfer_history(lib) do
    case Vws.CEC.Library.history(lib, limit: @history_rows) do
      {:ok, %{records: records, damaged: damaged}} ->
        %{
          damaged: length(damaged),
          rows:
            for r <- records do
              %{
                at: r.at,
                program:
                  "#{r.program} #{if r.version, do: "v#{r.version}", else: "(not in library)"}",
                direction: r.direction,
                command: r.command,
                bytes: r.bytes,
                blocks: r.blocks,
                ms: r.duration_ms,
                chars_per_s: r.chars_per_s,
                retries: r.retries,
                result: r.result,
                severity: if(String.starts_with?(r.result, "DONE"), do: "ok", else: "error"),
                requester: r.requester,
                note: r.note || ""
              }
            end
        }

      {:error, _} ->
        %{damaged: 0, rows: []}
    end
  end

  defp on_machine_class({:same, _}), do: "same"
  defp on_machine_class({:ambiguous, _}), do: "ambiguous"
  defp on_machine_class(other), do: to_string(other)

  defp partition(r) do
    status = Mailbox.status_word(r.status)

    %{
      name: String.upcase(to_string(r.partition)),
      state: Inspect.words(r.state),
      number: number(r.number),
      status: status,
      status_class: status |> String.split(" ") |> hd() |> String.downcase(),
      severity: severity(status),
      in_flight: number(r.in_flight),
      cmd_in: r.cmd_in,
      current: r.current && "#{number(r.current.number)} #{r.current.text}",
      running_ms: r.current && r.current.running_ms,
      done: r.done,
      errors: r.errors,
      restarts: r.restarts,
      link: Inspect.link_ref(r.link)
    }
  end

  defp devices(devices) do
    for d <- devices, d.name != "SPARE" or d.value != nil do
      text = Mailbox.device_text(d.value)

      %{
        location: d.location,
        name: d.name,
        value: text,
        age_ms: if(d.value == nil, do: nil, else: d.age_ms),
        no_data: text == nil or String.starts_with?(text, "NO DATA"),
        severity: severity(text)
      }
    end
  end

  @doc false
  # The numbers behind the device statuses: DAQ #1's latest poll (location 11) and the
  # hydraulic controller's latest PALLET? answer.
  def sensors(devices, readings) do
    sensors = Enum.find(devices, &(&1.location == 11))

    {poll, age, note, quantities, switches} =
      case sensors do
        %{value: %Vws.Links.DAQ.Readings{} = r, age_ms: age} ->
          quantities =
            for q <- Vws.Links.DAQ.Readings.quantities(r) do
              %{
                key: "daq1." <> to_string(q.signal),
                name: q.name,
                value: q.value && deadband(q.value, q.unit),
                raw: q.value && Float.round(q.value / 1, 3),
                unit: q.unit,
                source: "DAQ #1",
                note: if(q.open_circuit, do: "open circuit")
              }
            end

          switches =
            for {name, state} <- Vws.Links.DAQ.Readings.switches(r),
                do: %{name: name, state: state}

          {r.seq, age, nil, quantities, switches}

        %{value: value} ->
          {nil, nil, Mailbox.device_text(value) || "NO DATA (DAQ #1 NOT READ YET)", [], []}

        nil ->
          {nil, nil, nil, [], []}
      end

    {pallet_quantities, pallet_switches, pallet_age} = pallet(readings[:pallet])

    %{
      poll: poll,
      age_ms: age,
      note: note,
      quantities: quantities ++ pallet_quantities,
      switches: switches ++ pallet_switches,
      pallet_age_ms: pallet_age
    }
  end

  @doc """
  A value as the CEC judges it: within the partitions' noise band of zero
  (`Vws.Partitions.Fixture.noise_bands/0`: 0.5 mm, 25 N) it is 0, and it is written as the
  device statuses write it (mm with one decimal, N whole) — `-0.1 mm` is `0.0 mm`, `-25 N` is `0 N`.
  Other units: rounded to two decimals.
  """
  @spec deadband(number, String.t()) :: float | integer
  def deadband(v, "mm") do
    if abs(v) <= Vws.Partitions.Fixture.noise_bands().mm, do: 0.0, else: Float.round(v / 1, 1)
  end

  def deadband(v, "N") do
    if abs(v) <= Vws.Partitions.Fixture.noise_bands().n, do: 0, else: round(v)
  end

  def deadband(v, _unit), do: Float.round(v / 1, 2)

  # the hydraulic controller reports 9.9e37 N for a force it cannot read
  @overload_at 1.0e30

  defp pallet({%{force1_n: f1, force2_n: f2} = p, age}) do
    quantities =
      for {n, f} <- [{1, f1}, {2, f2}] do
        over = is_number(f) and f >= @overload_at

        %{
          key: "pallet.force#{n}_n",
          name: "pallet clamp force #{n}",
          value: if(is_number(f) and not over, do: deadband(f, "N")),
          raw: if(is_number(f) and not over, do: Float.round(f / 1, 1)),
          unit: "N",
          source: "hydraulic controller",
          note: if(over, do: "overload")
        }
      end

    switches =
      for key <- [:clamped, :x, :y], Map.has_key?(p, key) do
        %{name: "pallet #{key}", state: if(Map.get(p, key), do: "yes", else: "no")}
      end

    {quantities, switches, age}
  end

  defp pallet(_none), do: {[], [], nil}

  @doc false
  # A link row as the page shows it: name, state, counters, retries, last error, details.
  def link(r) do
    info = r.info || %{}
    line = Map.get(info, :line, %{})

    counters =
      numbers(Map.drop(info, [:line, :transfer, :address, :max_text, :pace]), "") ++
        numbers(
          Map.drop(line, [:a, :n, :r, :t, :window, :session, :outstanding, :queue]),
          "line "
        )

    retries =
      counters
      |> Enum.filter(&(&1.key =~ ~r/retr|retransmi/))
      |> Enum.map(& &1.value)
      |> Enum.sum()

    last_error =
      [info[:last_error], info[:error], line[:last_error], fault(info[:fault])]
      |> Enum.find(&(&1 != nil))

    state = Inspect.words(r.state)
    last_error = last_error && Inspect.words(last_error)

    %{
      id: r.name,
      state: state,
      state_class: if(state in @bad_states, do: "bad", else: "ok"),
      severity: link_severity(state, last_error),
      counters: counters,
      retries: retries,
      last_error: last_error,
      details:
        info
        |> Map.drop([:state, :last_error, :error, :fault, :line, :transfer, :device, :link])
        |> Enum.reject(fn {_k, v} -> is_number(v) or is_map(v) or v == nil or v == [] end)
        |> Enum.sort()
        |> Enum.map_join(", ", fn {k, v} -> "#{Inspect.words(k)} #{Inspect.words(v)}" end)
    }
  end

  defp fault(nil), do: nil
  defp fault(:none), do: nil
  defp fault(f), do: "fault injected: #{Inspect.words(f)}"

  # the numeric fields of an info map (and of its counters maps), as key/value pairs
  defp numbers(info, prefix) do
    info
    |> Enum.flat_map(fn
      {k, v} when is_integer(v) ->
        [%{key: prefix <> Inspect.words(k), value: v}]

      {k, %{} = m} when k in [:counters, :counts] ->
        for {c, v} <- m, is_integer(v), do: %{key: prefix <> Inspect.words(c), value: v}

      _ ->
        []
    end)
    |> Enum.sort_by(& &1.key)
  end

  defp wc(%{info: info, dialogue: dialogue}) do
    base =
      case info do
        %{} = i ->
          %{
            state: if(i.peer, do: "connected", else: "waiting"),
            endpoint: to_string(i.listening || i.endpoint || ""),
            peer: i.peer && to_string(i.peer),
            mode: Inspect.words(i.mode),
            counters: Map.new(i.counters, fn {k, v} -> {k, v} end),
            retries: Map.get(i.counters, :retransmissions, 0)
          }

        other ->
          %{
            state: Inspect.words(other),
            endpoint: nil,
            peer: nil,
            mode: nil,
            counters: %{},
            retries: 0
          }
      end

    lines =
      for {ms, dir, line} <- Enum.take(dialogue, -@dialogue_lines) do
        %{time: Inspect.clock(ms), dir: to_string(dir), line: Inspect.words(line)}
      end

    Map.put(base, :dialogue, lines)
  end

  defp transfers(snapshot, now) do
    wc =
      case snapshot.wc.info do
        %{transfer: %{} = t} -> [progress("WC", t.kind, t.number, :lines, t, now)]
        _ -> []
      end

    # NC programs only: the status reads of MONARCH's monitor are not transfers to follow. The
    # MONARCH command under way names the row (a program sent from the machine has none)
    monarch = Enum.find_value(snapshot.partitions, &(&1.partition == :monarch && &1.current))

    dnc =
      for %{id: :ge2000, info: %{transfer: %{} = t}} <- snapshot.links,
          kind = dnc_kind(t) do
        command = if kind != "FROM THE MACHINE", do: monarch
        row = progress("GE-2000 (DNC)", kind, command && command.number, :blocks, t, now)
        Map.merge(row, program_version(snapshot.workstation, t[:program], command))
      end

    wc ++ dnc
  end

  # Which program a transfer carries, and which version of the library: the one its command
  # names (`DOWNLOAD_GE(nnnnnn.PRO/v)`), else the library's latest (what `DOWNLOAD_GE(nnnnnn.PRO)`
  # sends, and what DOWNLOAD_HP stored last for the NC file); nil when the library has none.
  defp program_version(ws, program, command) do
    program = if program in [nil, ""], do: nc_file_program(ws), else: program

    named =
      case command && Regex.run(~r{/(\d+)\)\s*$}, command.text) do
        [_, v] -> String.to_integer(v)
        _ -> nil
      end

    version =
      named ||
        with true <- is_binary(program),
             {:ok, %{version: v}} <- Vws.CEC.Library.version(ws, program, :latest) do
          v
        else
          _ -> nil
        end

    %{program: program, version: version}
  end

  # the seed's DOWNLOAD_GE names no program on the line: the NC file's own (its first O word)
  defp nc_file_program(ws) do
    case Vws.Links.DNC.Program.file_name(Mailbox.nc_file(ws)) do
      {:ok, file} -> file
      {:error, _} -> nil
    end
  end

  defp dnc_kind(%{direction: :out, command: %{direction: :send, operation: :part_program}}),
    do: "DOWNLOAD_GE"

  defp dnc_kind(%{direction: :in, command: %{direction: :send, operation: :part_program}}),
    do: "FROM THE MACHINE"

  defp dnc_kind(%{command: %{direction: :receive, operation: :part_program}}), do: "UPLOAD_GE"
  defp dnc_kind(%{command: %{operation: :download_execute}}), do: "DRIP_FEED"
  defp dnc_kind(_other), do: nil

  @doc false
  # An NC transfer's progress from a link's `transfer` info: so far, in all, rate and ETA.
  def progress(link, kind, number, unit, t, now) do
    done = Map.get(t, unit) || 0
    total = Map.get(t, :"total_#{unit}")
    elapsed = max(now - t.started_ms, 1)
    rate = t.bytes * 1000 / elapsed

    eta =
      cond do
        t.total_bytes == nil -> nil
        t.bytes >= t.total_bytes -> 0
        rate > 0 -> Float.round((t.total_bytes - t.bytes) / rate, 1)
        true -> nil
      end

    %{
      link: link,
      kind: kind,
      number: number(number),
      unit: to_string(unit),
      done: done,
      total: total,
      bytes: t.bytes,
      total_bytes: t.total_bytes,
      percent: if(t.total_bytes, do: round(100 * t.bytes / max(t.total_bytes, 1))),
      elapsed_ms: elapsed,
      bytes_per_s: round(rate),
      eta_s: eta
    }
  end

  # a DAQ #1 poll older than this is stale: the numbers shown are not the equipment's now
  @stale_ms 30_000

  # What is wrong now (severity error) and what deserves a look (warning); never what is only
  # not read yet. Each with its severity.
  defp alerts(partitions, devices, links, wc, sensors) do
    for(
      p <- partitions,
      p.severity in ["error", "warning"],
      do: %{where: p.name, text: "#{p.number} #{p.status}", severity: p.severity}
    ) ++
      for(
        d <- devices,
        d.value != nil and d.severity in ["error", "warning"],
        do: %{where: d.name, text: d.value, severity: d.severity}
      ) ++
      for(
        l <- links,
        l.severity in ["error", "warning"],
        do: %{
          where: l.id,
          text: Enum.join(Enum.reject([l.state, l.last_error], &is_nil/1), ": last error "),
          severity: l.severity
        }
      ) ++
      if(sensors.poll != nil and is_integer(sensors.age_ms) and sensors.age_ms > @stale_ms,
        do: [
          %{
            where: "DAQ #1",
            text: "STALE READING (#{div(sensors.age_ms, 1000)} S OLD)",
            severity: "error"
          }
        ],
        else: []
      ) ++
      if(wc.state in ["waiting", "connected"],
        do: [],
        else: [%{where: "WC link", text: "SUN_COMM #{wc.state}", severity: "error"}]
      )
  end

  @doc "How bad a status or device text is: `Vws.Ops.Web.Severity.of/1`, the one place that decides it."
  @spec severity(String.t() | nil) :: String.t()
  defdelegate severity(text), to: Vws.Ops.Web.Severity, as: :of

  # a link that cannot be used is an error; one (re)connecting within its backoff, or working
  # with a last error to look at, a warning
  @link_errors ~w(down not_answering unreadable disconnected halted)
  @link_warnings ~w(connecting restarting)

  defp link_severity(state, last_error) do
    cond do
      state in @link_errors -> "error"
      state in @link_warnings -> "warning"
      last_error != nil -> "warning"
      true -> "ok"
    end
  end

  @doc false
  # The text a workstation id is shown (and addressed) by.
  def label(ws), do: Vws.Ops.MTConnect.Model.device_name(ws)

  defp number(nil), do: nil
  defp number(:unknown), do: "unknown (journal damaged)"
  defp number(n), do: Vws.Codecs.WC.Command.pad4(n)
end
