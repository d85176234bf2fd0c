defmodule Vws.Ops.Inspect do
  @moduledoc """
  One-call live views of a running workstation, for iex (`iex -S mix vws.serve`), and the plain
  data behind the web dashboard.

      iex> Vws.Ops.Inspect.overview("VWS")            # everything below, one after the other
      iex> Vws.Ops.Inspect.mailboxes("VWS")           # device status 1–14, command status 34–39, CMD_IN
      iex> Vws.Ops.Inspect.partitions("VWS")          # state, current command, done/errors, restarts
      iex> Vws.Ops.Inspect.links("VWS")               # each device link: state, counters, last error
      iex> Vws.Ops.Inspect.interlocks("VWS")          # who holds the table, the trays, …
      iex> Vws.Ops.Inspect.transfers("VWS")           # the transfer history (issue 27), newest first
      iex> Vws.Ops.Inspect.transfers("VWS", program: "4711", limit: 10)
      iex> Vws.Ops.Inspect.watch("VWS", :robot)       # a partition's traffic live, until Enter
      iex> Vws.Ops.Inspect.watch("VWS", :wc, timeout: 10_000)   # the WC dialogue for ten seconds

  The views print a table and return `:ok`; `snapshot/1` and the `*_rows/1` functions return the
  same facts as data. None of them ever blocks on a busy process for long: a partition, link or
  SUN_COMM that does not answer within half a second is shown as `not answering`, one that is not
  running as `down`.

  ## What is shown

    * **partitions** — each command partition's process state (`idle`, `running`, `down`), its
      command status (mailbox 34–39), the command in flight and for how long, commands done and
      ended in error since it started, and its restarts;
    * **links** — every child of the workstation's links supervisor: what it is
      (`link_name/2`: `DAQ #1 (HPIB 9)`, `GE-2000 (DNC)`, …), its pid, state and, when its module
      exports `info/1`, that map (counters, last error, …). Every link module's `info/1` takes
      the link's pid; one that cannot be read (its `info/1` raises) is shown `unreadable` with
      the error, and the other rows are shown all the same;
    * **interlocks** — every interlock lease (`Vws.CEC.Interlock.held/1`): volume, holder, reasons,
      age.

  Everything printed is words and numbers (`words/1`), never an Elixir term.
  """

  alias Vws.CEC.{Events, Mailbox}

  @call_timeout 500

  @typedoc "A workstation id."
  @type workstation :: term

  ## Data

  @doc """
  A snapshot of every mailbox (`Vws.CEC.Mailbox`) as plain data: device status 1–14, command status
  34–39 with CMD_IN and the command in flight, the last string, the programs, the interlock
  leases and the events caused.
  """
  @spec mailbox_snapshot(workstation) :: map
  def mailbox_snapshot(ws) do
    devices =
      for loc <- 1..14 do
        {value, age} = Mailbox.get_device(ws, loc)
        %{location: loc, name: Mailbox.device_name(loc), value: value, age_ms: age}
      end

    commands =
      for p <- Mailbox.partitions() do
        {number, status} = Mailbox.command_status(ws, p)
        {in_number, in_text} = Mailbox.cmd_in(ws, p)

        %{
          location: Mailbox.command_location(p),
          partition: p,
          number: number,
          status: status,
          cmd_in: {in_number, in_text},
          in_flight: Mailbox.in_flight(ws, p)
        }
      end

    {seq, _} = Mailbox.last_string(ws)

    %{
      workstation: ws,
      devices: devices,
      commands: commands,
      last_sequence: seq,
      nc_file: Mailbox.nc_file(ws),
      nc_up: Mailbox.nc_up(ws),
      interlocks: Vws.CEC.Interlock.held(ws),
      events: Events.list(ws)
    }
  end

  @doc """
  Everything about a workstation as plain data: `%{workstation, mailboxes, partitions, links,
  interlocks, wc: %{info, dialogue}}` (`mailboxes` is `mailbox_snapshot/1`).
  """
  @spec snapshot(workstation) :: map
  def snapshot(ws) do
    %{
      workstation: ws,
      mailboxes: mailbox_snapshot(ws),
      partitions: partition_rows(ws),
      links: link_rows(ws),
      interlocks: interlock_rows(ws),
      wc: %{info: wc_info(ws), dialogue: wc_dialogue(ws)}
    }
  end

  @doc """
  One map per command partition: `partition, state (:idle | :running | :down | :not_answering),
  number, status, in_flight, cmd_in, current (nil | %{number, text, running_ms}), done, errors,
  restarts, link`.
  """
  @spec partition_rows(workstation) :: [map]
  def partition_rows(ws) do
    Mailbox.partitions()
    |> parallel(fn p ->
      {p, Vws.CEC.Partition.whereis(ws, p) && call(fn -> Vws.CEC.Partition.info(ws, p) end)}
    end)
    |> Enum.map(fn {p, info} ->
      {number, status} = Mailbox.command_status(ws, p)
      {_in_n, in_text} = Mailbox.cmd_in(ws, p)

      state =
        case info do
          nil -> :down
          :down -> :down
          :not_answering -> :not_answering
          {:unreadable, _} -> :unreadable
          %{current: nil} -> :idle
          %{current: _} -> :running
        end

      info = if is_map(info), do: info, else: %{}

      %{
        partition: p,
        state: state,
        number: number,
        status: status,
        in_flight: Mailbox.in_flight(ws, p),
        cmd_in: in_text,
        current: info[:current],
        done: info[:done],
        errors: info[:errors],
        restarts: info[:restarts] || restarts(ws, p),
        link: info[:link]
      }
    end)
  end

  defp restarts(ws, p) do
    case :ets.lookup(Mailbox.table(ws), {:starts, p}) do
      [{_, n}] -> max(n - 1, 0)
      [] -> 0
    end
  end

  @doc """
  One map per device link (child of the workstation's links supervisor): `id, pid, module, state,
  info` — `state` is the `:state` of the link's `info/1` map when it has one, else `:running`,
  `:restarting`, `:down` or `:not_answering`; `info` is that map or nil.
  """
  @spec link_rows(workstation) :: [map]
  def link_rows(ws) do
    case Vws.CEC.Workstation.whereis(ws, :links) do
      nil ->
        []

      sup ->
        children =
          case call(fn -> Supervisor.which_children(sup) end) do
            list when is_list(list) -> list
            _ -> []
          end

        children
        |> parallel(&link_row/1)
        |> Enum.sort_by(& &1.name)
    end
  end

  defp link_row({id, pid, _type, modules}) do
    module = if is_list(modules), do: List.first(modules)

    {state, info} =
      cond do
        pid == :restarting ->
          {:restarting, nil}

        not is_pid(pid) ->
          {:down, nil}

        module && Code.ensure_loaded?(module) && function_exported?(module, :info, 1) ->
          case call(fn -> module.info(pid) end) do
            %{} = info -> {Map.get(info, :state, :running), info}
            :not_answering -> {:not_answering, nil}
            :down -> {:down, nil}
            {:unreadable, why} -> {:unreadable, %{error: why}}
            other -> {:running, %{info: other}}
          end

        true ->
          {:running, nil}
      end

    %{
      id: id,
      name: link_name(id, info),
      pid: if(is_pid(pid), do: pid),
      module: module,
      state: state,
      info: info
    }
  end

  @doc """
  Equipment of the cell that runs on this node outside any workstation — the hydraulic
  controller (`Vws.Peers.HydraulicController`, on the simulated floor or started with
  `mix vws.hydraulic`) — with its own link to DAQ #2: `[%{name, state, info, links}]`, `links`
  shaped as `link_rows/1`.
  """
  @spec equipment_rows() :: [map]
  def equipment_rows do
    Registry.select(Vws.Registry, [
      {{{{:hydraulic_controller, :"$1"}, :program}, :_, :_}, [], [:"$1"]}
    ])
    |> Enum.sort_by(&inspect/1)
    |> Enum.map(fn name ->
      info = call(fn -> Vws.Peers.HydraulicController.info(name) end)
      {bus, address} = Vws.Peers.HydraulicController.daq2_device(name)

      daq2 =
        link_row(
          {{Vws.Links.HPIB, bus, address}, Vws.Links.HPIB.whereis({bus, address}) || :undefined,
           :worker, [Vws.Links.HPIB]}
        )

      %{
        name: "hydraulic controller #{words(name)}",
        state: if(is_map(info), do: Map.get(info, :phase, :running), else: info),
        info: if(is_map(info), do: info),
        links: [daq2]
      }
    end)
  end

  @doc """
  The device link a partition was given, for people: `"VAL II"`, `"GE-2000"`, `"HPIB 9"`,
  `"none"`.
  """
  @spec link_ref(term) :: String.t()
  def link_ref(nil), do: "none"
  def link_ref({_bus, address}) when is_integer(address), do: "HPIB #{address}"

  def link_ref(name) do
    case Vws.Names.role_of(name) do
      :val -> "VAL II"
      :ge2000 -> "GE-2000"
      nil -> words(name)
      role -> words(role)
    end
  end

  @doc """
  What a link is, for people: `"DAQ #1 (HPIB 9)"`, `"GE-2000 (DNC)"`, `"VAL II (DDCMP)"`, … —
  from the link's id under the links supervisor and its `info/1` map (an HPIB device says what
  it is through its `:device` option).
  """
  @spec link_name(term, map | nil) :: String.t()
  def link_name({Vws.Links.HPIB, _bus, address}, info) do
    case info do
      %{device: device} when is_binary(device) -> "#{device} (HPIB #{address})"
      _ -> "HPIB device #{address}"
    end
  end

  def link_name(:ge2000, _info), do: "GE-2000 (DNC)"
  def link_name(:val, _info), do: "VAL II (DDCMP)"
  def link_name(Vws.Partitions.Monarch.Monitor, _info), do: "MONARCH status reader"
  def link_name(Vws.Partitions.Hydraulic.Monitor, _info), do: "PALLET status reader"
  def link_name(id, _info), do: label(id)

  @doc """
  Every interlock lease of the workstation (`Vws.CEC.Interlock.held/1`), by volume:
  `%{what, holder, reasons, age_ms}` — `what` is the volume (`:table`, `:tray1`, …).
  """
  @spec interlock_rows(workstation) :: [map]
  def interlock_rows(ws) do
    for lease <- Vws.CEC.Interlock.held(ws) do
      %{what: lease.volume, holder: lease.holder, reasons: lease.reasons, age_ms: lease.age_ms}
    end
  end

  @doc "SUN_COMM's `info/1` map, or `:down` / `:not_answering`."
  @spec wc_info(workstation) :: map | :down | :not_answering
  def wc_info(ws) do
    if Vws.CEC.Workstation.whereis(ws, :sun_comm),
      do: call(fn -> Vws.CEC.SunComm.info(ws) end),
      else: :down
  end

  @doc "The recent WC dialogue (`Vws.CEC.SunComm.dialogue/1`), `[]` when SUN_COMM is not answering."
  @spec wc_dialogue(workstation) :: [{integer, :in | :out, binary}]
  def wc_dialogue(ws) do
    with pid when is_pid(pid) <- Vws.CEC.Workstation.whereis(ws, :sun_comm),
         list when is_list(list) <- call(fn -> Vws.CEC.SunComm.dialogue(ws) end) do
      list
    else
      _ -> []
    end
  end

  ## Printed views

  @doc "Prints the mailboxes (from iex: `Vws.Ops.Inspect.mailboxes(\"VWS1\")`)."
  @spec mailboxes(workstation) :: :ok
  def mailboxes(ws), do: IO.puts(format_mailboxes(ws))

  @doc "The table `mailboxes/1` prints, as a string."
  @spec format_mailboxes(workstation) :: String.t()
  def format_mailboxes(ws) do
    s = mailbox_snapshot(ws)

    device_rows =
      for d <- s.devices do
        [pad(d.location, 4), pad(d.name, 12), pad(device_age(d), 9), device_value(d.value)]
      end

    command_rows =
      for c <- s.commands do
        {in_n, in_text} = c.cmd_in

        [
          pad(c.location, 4),
          pad(String.upcase(to_string(c.partition)), 10),
          pad(number(c.number), 6),
          pad(Mailbox.status_word(c.status), 24),
          pad(if(c.in_flight, do: number(c.in_flight), else: "-"), 10),
          if(in_n, do: "#{number(in_n)} #{in_text}", else: "-")
        ]
      end

    [
      "VWS mailboxes of workstation #{inspect(ws)}   last string: #{number(s.last_sequence)}",
      "",
      "DEVICE STATUS",
      "loc name         age      value",
      Enum.map(device_rows, &Enum.join/1),
      "",
      "COMMAND STATUS",
      "loc partition  last   status                  in flight CMD_IN",
      Enum.map(command_rows, &Enum.join/1),
      "",
      "NC file: #{length(s.nc_file)} lines   NC_UP: #{length(s.nc_up)} lines",
      "INTERLOCKS: " <> format_leases(s.interlocks),
      "EVENTS: " <> Enum.map_join(s.events, "  ", fn {e, n} -> "#{e}=#{n}" end)
    ]
    |> List.flatten()
    |> Enum.join("\n")
  end

  defp pad(v, n), do: v |> to_string() |> String.pad_trailing(n)
  defp device_age(%{value: nil}), do: "-"
  defp device_age(%{age_ms: ms}) when ms < 10_000, do: "#{ms}ms"
  defp device_age(%{age_ms: ms}), do: "#{div(ms, 1000)}s"
  defp device_value(nil), do: "(no data)"
  defp device_value(v), do: Mailbox.device_text(v)

  @doc """
  The interlock leases (`Vws.CEC.Interlock.held/1`) as one line of text:
  `TABLE=ROBOT,FIXTURE TRAY1=MHS` (`NONE` when free).
  """
  @spec format_leases([Vws.CEC.Interlock.lease()]) :: String.t()
  def format_leases([]), do: "NONE"

  def format_leases(leases) do
    leases
    |> Enum.chunk_by(& &1.volume)
    |> Enum.map_join(" ", fn [%{volume: v} | _] = group ->
      "#{Vws.CEC.Interlock.name(v)}=" <>
        Enum.map_join(group, ",", &Vws.CEC.Interlock.name(&1.holder))
    end)
  end

  @doc "Prints the cell view: every workstation of the cell (`Vws.CEC.Cell.workstations/0`)."
  @spec cell() :: :ok
  def cell, do: IO.puts(format_cell(Vws.CEC.Cell.workstations()))

  @doc "The cell view `cell/0` prints: one line per workstation, then how many on how many nodes."
  @spec format_cell([Vws.CEC.Cell.workstation()]) :: String.t()
  def format_cell(workstations) do
    rows =
      for ws <- workstations do
        wc =
          case ws do
            %{wc: nil} -> "-"
            %{wc: wc, wc_connected: true} -> "#{wc} (WC on)"
            %{wc: wc} -> wc
            _ -> "?"
          end

        [cell_id(ws.id), to_string(ws.node), to_string(ws.state), wc, in_flight(ws)]
      end

    nodes = workstations |> Enum.uniq_by(& &1.node) |> length()

    Vws.Ops.TextTable.render(["ID", "NODE", "STATE", "WC", "COMMANDS IN FLIGHT"], rows) <>
      "\n#{length(rows)} workstation(s) on #{nodes} node(s)"
  end

  defp in_flight(%{commands: commands}) do
    case for({p, {n, :executing}} <- commands, do: "#{p} #{number(n)}") do
      [] -> "-"
      list -> Enum.join(list, ", ")
    end
  end

  defp in_flight(_), do: "?"

  defp cell_id(id) when is_binary(id), do: id
  defp cell_id(id), do: inspect(id)

  @doc """
  Prints the transfer history of `ws`'s program library (`Vws.CEC.Library.history/2`: options
  `:program`, `:limit`), newest first, and any damaged part that was skipped.
  """
  @spec transfers(workstation, keyword) :: :ok
  def transfers(ws, opts \\ []), do: Vws.Ops.LibraryText.print_history(ws, opts)

  @doc "Prints the partitions table."
  @spec partitions(workstation) :: :ok
  def partitions(ws), do: IO.puts(format_partitions(ws))

  @doc "Prints the links table."
  @spec links(workstation) :: :ok
  def links(ws), do: IO.puts(format_links(ws))

  @doc "Prints the interlocks table."
  @spec interlocks(workstation) :: :ok
  def interlocks(ws), do: IO.puts(format_interlocks(ws))

  @doc "Prints the WC link (peer, mode, counters) and its last `n` dialogue lines."
  @spec wc(workstation, pos_integer) :: :ok
  def wc(ws, n \\ 20), do: IO.puts(format_wc(ws, n))

  @doc "Prints every view of a workstation."
  @spec overview(workstation) :: :ok
  def overview(ws) do
    IO.puts(
      Enum.join(
        [
          format_mailboxes(ws),
          format_partitions(ws),
          format_links(ws),
          format_interlocks(ws),
          format_wc(ws, 10)
        ],
        "\n\n"
      )
    )
  end

  @doc "The table `partitions/1` prints."
  @spec format_partitions(workstation) :: String.t()
  def format_partitions(ws) do
    rows =
      for r <- partition_rows(ws) do
        current =
          case r.current do
            %{number: n, text: t, running_ms: ms} -> "#{number(n)} #{t} (#{ms} ms)"
            nil -> "-"
          end

        [
          String.upcase(to_string(r.partition)),
          to_string(r.state),
          "#{number(r.number)} #{Mailbox.status_word(r.status)}",
          current,
          count(r.done),
          count(r.errors),
          to_string(r.restarts),
          link_ref(r.link)
        ]
      end

    table(
      "PARTITIONS of #{inspect(ws)}",
      ["partition", "state", "command status", "running", "done", "errors", "restarts", "link"],
      rows
    )
  end

  @doc "The table `links/1` prints."
  @spec format_links(workstation) :: String.t()
  def format_links(ws) do
    rows =
      for r <- link_rows(ws) do
        [
          r.name,
          if(r.pid, do: inspect(r.pid), else: "-"),
          label(r.state),
          format_info(r.info)
        ]
      end

    if rows == [],
      do: "LINKS of #{inspect(ws)}\n(no device links configured)",
      else: table("LINKS of #{inspect(ws)}", ["link", "pid", "state", "info"], rows)
  end

  @doc "The table `interlocks/1` prints."
  @spec format_interlocks(workstation) :: String.t()
  def format_interlocks(ws) do
    rows =
      for r <- interlock_rows(ws) do
        [label(r.what), holder(r.holder), Enum.map_join(r.reasons, " ", &label/1), age(r.age_ms)]
      end

    if rows == [],
      do: "INTERLOCKS of #{inspect(ws)}\n(none held)",
      else: table("INTERLOCKS of #{inspect(ws)}", ["interlock", "holder", "for", "held"], rows)
  end

  @doc "The text `wc/2` prints."
  @spec format_wc(workstation, pos_integer) :: String.t()
  def format_wc(ws, n \\ 20) do
    head =
      case wc_info(ws) do
        %{} = i ->
          counters = Enum.map_join(Enum.sort(i.counters), " ", fn {k, v} -> "#{k}=#{v}" end)

          "WC LINK of #{inspect(ws)}: #{i.listening || i.endpoint || "no endpoint"}, " <>
            "peer #{i.peer || "none"}, mode #{words(i.mode)}\n#{counters}"

        other ->
          "WC LINK of #{inspect(ws)}: SUN_COMM #{label(other)}"
      end

    lines =
      ws
      |> wc_dialogue()
      |> Enum.take(-n)
      |> Enum.map(fn {ms, dir, line} -> "#{clock(ms)} #{arrow(dir)} #{printable(line)}" end)

    Enum.join([head | lines], "\n")
  end

  ## Watching live

  @doc """
  Prints a workstation's traffic as it happens: for a partition (`:robot`, `:monarch`, …) every
  telemetry event about it (commands dispatched, started, finished) and its device's traffic —
  for `:robot` every VAL II message both ways (`VAL II → LUN 1 write: DO MOVE …`) and the
  DDCMP link's events (NAKs, REPs, retransmissions, state changes; not each frame), for
  `:monarch` the GE-2000's DNC link — for `:wc` every line of the WC dialogue and SUN_COMM's
  events, for `:all` everything.

  It prints until Enter is pressed (in iex) or for `:timeout` ms (when given, or 30 s outside
  iex; a message `:stop_watch` to the watching process ends it sooner), then returns the number
  of lines printed. Options: `:timeout`, `:device` (default the group leader).
  """
  @spec watch(workstation, atom, keyword) :: non_neg_integer
  def watch(ws, target, opts \\ []) do
    device = Keyword.get(opts, :device, Process.group_leader())
    Mailbox.table(ws)
    me = self()
    ref = make_ref()

    watcher =
      spawn_link(fn ->
        id = {__MODULE__, :watch, self()}
        subscribe(ws, target)

        Vws.Telemetry.attach_many(id, Vws.Telemetry.events(), &__MODULE__.forward/4, %{
          pid: self(),
          ws: ws,
          target: target
        })

        send(me, {ref, :ready})

        try do
          watch_loop(ws, device, 0)
        after
          Vws.Telemetry.detach(id)
        end
      end)

    receive do
      {^ref, :ready} -> :ok
    end

    interactive? =
      Code.ensure_loaded?(IEx) and IEx.started?() and not Keyword.has_key?(opts, :timeout)

    if interactive? do
      IO.puts(device, "watching #{inspect(ws)} #{target}: press Enter to stop")
      IO.gets("")
    else
      timeout = Keyword.get(opts, :timeout, 30_000)
      IO.puts(device, "watching #{inspect(ws)} #{target} for #{timeout} ms")

      receive do
        :stop_watch -> :ok
      after
        timeout -> :ok
      end
    end

    wref = Process.monitor(watcher)
    send(watcher, {:stop, me, ref})

    receive do
      {^ref, :printed, n} ->
        Process.demonitor(wref, [:flush])
        n

      {:DOWN, ^wref, _, _, _} ->
        0
    end
  end

  defp subscribe(ws, target) do
    if target in [:wc, :all], do: Events.subscribe(ws, :wc_dialogue)
    if target not in [:wc, :all], do: Events.subscribe(ws, target)
  end

  @doc false
  # A telemetry handler (runs in the emitting process): forwards the workstation's events about
  # the target to the watcher.
  def forward(event, measurements, metadata, %{pid: pid, ws: ws, target: target}) do
    if Map.get(metadata, :workstation) == ws and about?(event, metadata, target) do
      send(pid, {:watch_telemetry, event, measurements, metadata})
    end
  end

  defp about?(_event, _meta, :all), do: true
  defp about?([:vws, :sun_comm | _], _meta, :wc), do: true
  defp about?(_event, _meta, :wc), do: false

  defp about?(event, meta, target),
    do: Map.get(meta, :partition) == target or target in event or device_traffic?(event, target)

  # The device a partition drives: its link's events (the workstation is in their metadata).
  defp device_traffic?([:vws, :ddcmp, frame], :robot)
       when frame in [:frame_sent, :frame_received],
       do: false

  defp device_traffic?([:vws, link | _], :robot), do: link in [:val, :ddcmp]
  defp device_traffic?([:vws, link | _], :monarch), do: link == :dnc
  defp device_traffic?(_event, _target), do: false

  defp watch_loop(ws, device, n) do
    receive do
      {:vws_event, ^ws, :wc_dialogue, {ms, dir, line}} ->
        IO.puts(device, "#{clock(ms)} WC #{arrow(dir)} #{printable(line)}")
        watch_loop(ws, device, n + 1)

      {:vws_event, ^ws, event, payload} ->
        IO.puts(device, "#{clock(now())} EVENT #{event} caused (#{inspect(payload)})")
        watch_loop(ws, device, n + 1)

      {:watch_telemetry, event, measurements, metadata} ->
        IO.puts(device, "#{clock(now())} " <> telemetry_line(event, measurements, metadata))
        watch_loop(ws, device, n + 1)

      {:stop, from, ref} ->
        send(from, {ref, :printed, n})
    end
  end

  @doc false
  def telemetry_line([:vws, :val, :message], _measurements, %{direction: dir} = m) do
    arrow = if dir == :out, do: "→", else: "←"
    qualifier = if m.function == :write, do: "", else: " #{short(m.qualifier)}"

    "VAL II #{arrow} LUN #{m.lun} #{m.function}#{qualifier}: " <>
      printable(to_string(Map.get(m, :text, "")))
  end

  def telemetry_line(event, measurements, metadata) do
    name = event |> Enum.drop(1) |> Enum.join(".")

    meta =
      metadata
      |> Map.drop([:workstation, :stacktrace])
      |> Enum.sort()
      |> Enum.map_join(" ", fn {k, v} -> "#{k}=#{short(v)}" end)

    measured =
      measurements
      |> Enum.sort()
      |> Enum.map_join(" ", fn
        {:duration, d} -> "duration=#{System.convert_time_unit(d, :native, :millisecond)}ms"
        {k, v} -> "#{k}=#{short(v)}"
      end)

    String.trim("#{name} #{meta} #{measured}")
  end

  ## Helpers

  # Runs fun with a deadline: its result; :down (the process exited or is not there);
  # :not_answering (no answer in time); {:unreadable, why} when asking raised — one row that
  # cannot be read says so and never takes the view (or the shell that asked) down with it.
  defp call(fun) do
    task = Task.async(fn -> try_call(fun) end)

    case Task.yield(task, @call_timeout) || Task.shutdown(task, :brutal_kill) do
      {:ok, {:ok, result}} -> result
      {:ok, :down} -> :down
      {:ok, {:unreadable, _} = unreadable} -> unreadable
      _ -> :not_answering
    end
  end

  defp try_call(fun) do
    {:ok, fun.()}
  catch
    :exit, _ -> :down
    kind, reason -> {:unreadable, Exception.format_banner(kind, reason) |> first_line()}
  end

  defp first_line(text), do: text |> String.split("\n", parts: 2) |> hd() |> String.slice(0, 160)

  defp parallel(list, fun) do
    list
    |> Task.async_stream(fun, timeout: @call_timeout * 3, on_timeout: :kill_task)
    |> Enum.zip(list)
    |> Enum.map(fn
      {{:ok, result}, _} -> result
      {{:exit, _}, item} -> fun_failed(item)
    end)
  end

  defp fun_failed(p) when is_atom(p), do: {p, :not_answering}

  defp fun_failed({id, _pid, _type, modules}),
    do: %{
      id: id,
      name: link_name(id, nil),
      pid: nil,
      module: List.first(List.wrap(modules)),
      state: :not_answering,
      info: nil
    }

  defp table(title, header, rows), do: title <> "\n" <> Vws.Ops.TextTable.render(header, rows)

  @doc false
  # A short human label for an id, state or interlock name: :table -> "table", {:tray, 1} -> "tray 1".
  def label(a) when is_atom(a), do: to_string(a)
  def label(b) when is_binary(b), do: b
  def label(n) when is_integer(n), do: Integer.to_string(n)

  def label(t) when is_tuple(t) and tuple_size(t) > 0 do
    t |> Tuple.to_list() |> Enum.map_join(" ", &label/1)
  end

  def label(other), do: inspect(other, limit: 8)

  @doc """
  Any value as words a person reads, never an Elixir term: text as it is, atoms and numbers as
  they read, tuples and lists joined with spaces, maps as `key value` pairs, an exception as
  its message, a process as `process`.

      iex> Vws.Ops.Inspect.words({:ready, :still})
      "ready still"
      iex> Vws.Ops.Inspect.words(%{a: 1, b: [:x, "Y"]})
      "a 1, b x Y"
  """
  @spec words(term) :: String.t()
  def words(nil), do: "-"
  def words(v) when is_binary(v), do: if(String.printable?(v), do: v, else: inspect(v))
  def words(v) when is_atom(v), do: v |> to_string() |> String.replace("_", " ")
  def words(v) when is_integer(v), do: Integer.to_string(v)
  def words(v) when is_float(v), do: :erlang.float_to_binary(v, [:compact, decimals: 3])
  def words(v) when is_pid(v) or is_reference(v) or is_port(v), do: "process"
  def words(%{__exception__: true} = e), do: Exception.message(e)
  def words(%Vws.Links.DAQ.Readings{} = r), do: Vws.Links.DAQ.Readings.describe(r)
  def words(%_{} = struct), do: struct |> Map.from_struct() |> words()

  def words(%{} = m),
    do: m |> Enum.sort() |> Enum.map_join(", ", fn {k, v} -> "#{words(k)} #{words(v)}" end)

  def words(t) when is_tuple(t), do: t |> Tuple.to_list() |> Enum.map_join(" ", &words/1)

  def words(l) when is_list(l) do
    if l != [] and List.ascii_printable?(l),
      do: List.to_string(l),
      else: Enum.map_join(l, " ", &words/1)
  end

  def words(other), do: inspect(other, limit: 8)

  @doc false
  # A duration for people: "850 ms", "12 s", "3 min".
  def age(nil), do: "-"
  def age(ms) when ms < 10_000, do: "#{ms} ms"
  def age(ms) when ms < 600_000, do: "#{div(ms, 1000)} s"
  def age(ms), do: "#{div(ms, 60_000)} min"

  defp holder(nil), do: "-"
  defp holder(h), do: label(h)

  defp format_info(nil), do: ""

  defp format_info(info) do
    info
    |> Map.drop([:state])
    |> Enum.sort()
    |> Enum.map_join("  ", fn
      {k, %{} = m} ->
        "#{k}: " <> Enum.map_join(Enum.sort(m), " ", fn {a, b} -> "#{a}=#{short(b)}" end)

      {k, v} ->
        "#{k}=#{short(v)}"
    end)
  end

  defp short(v) when is_binary(v), do: printable(v)
  defp short(v) when is_atom(v) or is_number(v), do: to_string(v)
  defp short(v), do: words(v)

  defp count(nil), do: "-"
  defp count(n), do: to_string(n)

  defp number(nil), do: "----"
  defp number(:unknown), do: "UNKNOWN (JOURNAL DAMAGED)"
  defp number(n), do: Vws.Codecs.WC.Command.pad4(n)

  defp arrow(:in), do: "→"
  defp arrow(:out), do: "←"

  defp printable(line) do
    if String.printable?(line), do: line, else: inspect(line)
  end

  defp now, do: System.monotonic_time(:millisecond)

  @doc false
  # Wall-clock time of a monotonic millisecond stamp, as HH:MM:SS.mmm.
  def clock(monotonic_ms) do
    (monotonic_ms + System.time_offset(:millisecond))
    |> DateTime.from_unix!(:millisecond)
    |> DateTime.to_time()
    |> Time.to_string()
    |> String.pad_trailing(12, "0")
  end
end
