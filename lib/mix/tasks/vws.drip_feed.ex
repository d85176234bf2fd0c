defmodule Mix.Tasks.Vws.DripFeed do
  @shortdoc "Drip-feeds an NC program to a GE-2000 (DNC E: download and execute)"
  @moduledoc """
  Streams an NC program to a GE-2000 over the DNC Level 2 link as one `E` (download and
  execute) transmission: the machine runs it while it arrives and pauses the sender with WACK
  when its block buffer is full, so a program larger than its memory can run
  (docs/dnc-drip-feed.md). Progress is printed every second; the exit status is 0 only when the
  whole program reached the machine.

      mix vws.drip_feed part.nc --ge2000 tty:/dev/ttyS1?baud=4800   # a real machine
      mix vws.drip_feed part.nc                                    # the simulated GE-2000
      mix vws.drip_feed part.nc --baud 4800 --memory 8192 --feed-rate 400

  The program must hold its program number (`O`/`:` word) and end with its `%` line.

  From the program library (issue 27), as the WC's `DRIP_FEED(nnnnnn.PRO[/v][/Nk])` takes it —
  only a **released** version, restarted at line k with the modal state of the lines before it
  restored (`Vws.Partitions.Monarch.restart/4`, `Vws.Codecs.NCModal`):

      mix vws.drip_feed --program 4711                      # the latest released version
      mix vws.drip_feed --program 004711.PRO --version 3    # version 3, if released
      mix vws.drip_feed --program 4711 --line 600           # restarted at line 600
      mix vws.drip_feed part.nc --line 600                  # a file restarted at line 600

  A restart prints the preamble it sends before line k (the program's head, a comment naming
  the restart, then the lines restoring units, plane, distance mode, work offset, tool, spindle,
  coolant, motion and feed) **before a block goes**. Refused with nothing sent, in the words the
  WC would see and exit status 1: a program not in the library or with no released version, a
  draft version (`000077.PRO VERSION 2 NOT RELEASED`), a line past the end or inside a canned
  cycle (`RESTART LINE 410 INSIDE A CANNED CYCLE G81 (NO G80 BEFORE IT)`).

  Options:

    * `--ge2000 ENDPOINT` — the machine's DNC line (`tty:…`, `tcp://…`); without it a simulated
      GE-2000 (`Vws.Sim.GE2000`) is started, and its drip-feed figures are printed at the end
    * `--baud N` — pace the simulated machine's line at N Bd (default: unpaced)
    * `--memory N`, `--feed-rate N` — the simulated machine's block buffer (bytes) and the rate it
      runs the program at (characters a second)
    * `--check lrc|crc` — the block check (default crc)
    * `--max-text N` — text bytes per block (default 256)
    * `--program NAME` — a program of the library instead of a file (`4711`, `O4711`,
      `004711.PRO`); `--version V` a version of it (default: the latest released)
    * `--line K` — restart at line K (lines counted as the library's: 1 is the leading `%`)
    * `--library DIR`, `--id ID` — which library, as `mix vws.library`'s: `DIR`, else
      `library/<id>` of the data directory (`--id`, default `$VWS_ID`, else `VWS`)
  """
  use Mix.Task

  alias Vws.Links.DNC
  alias Vws.Links.DNC.{Frame, LinkError, Program}
  alias Vws.Links.DNC.Frame.Command

  @switches [
    ge2000: :string,
    baud: :pos_integer,
    memory: :pos_integer,
    feed_rate: :pos_integer,
    check: {:in, ["lrc", "crc"]},
    max_text: :pos_integer,
    program: :string,
    version: :pos_integer,
    line: :pos_integer,
    library: :string,
    id: :string
  ]

  @impl true
  def run(args) do
    {opts, rest} = Vws.CLIOptions.parse!(args, @switches, args: true)
    {name, text} = program(rest, opts)

    check = if opts[:check] == "lrc", do: :lrc, else: :crc
    max_text = opts[:max_text] || 256

    Mix.Task.run("app.start")
    # one Ctrl-C in this terminal: an ordered stop, never the BEAM's BREAK menu (which freezes it)
    Vws.Ops.Signals.ctrl_c_stops()

    {endpoint, sim} =
      case opts[:ge2000] do
        nil -> simulated(opts, max_text)
        endpoint -> {endpoint, nil}
      end

    {:ok, link} = DNC.start_link(endpoint: endpoint, max_text: max_text)
    await_link(link, 50)

    command = %Command{direction: :send, check: check, operation: :download_execute, text: name}
    blocks = Frame.split_text(text, max_text)
    Mix.shell().info("drip feed of #{name}: #{byte_size(text)} bytes in #{length(blocks)} blocks")
    task = Task.async(fn -> DNC.request(link, command, blocks, :infinity) end)
    result = follow(task, link)

    case result do
      {:ok, _} ->
        Mix.shell().info("#{name}: the whole program reached the machine")
        if sim, do: report_machine(sim)

      {:error, %LinkError{} = e} ->
        Mix.shell().error("#{name}: ERROR #{LinkError.status_text(e)}")
        exit({:shutdown, 1})
    end
  end

  # {file name, the text to send}: a file, or a library program as DRIP_FEED(…) reads it;
  # restarted at --line with its preamble printed before anything is sent
  defp program([file], opts) do
    if opts[:program] || opts[:version], do: usage()

    text =
      case File.read(file) do
        {:ok, text} -> text
        {:error, reason} -> Mix.raise("#{file}: #{:file.format_error(reason)}")
      end

    lines = Program.from_text(text)

    name =
      case Program.file_name(lines) do
        {:ok, name} -> name
        {:error, why} -> Mix.raise("#{file}: #{why}")
      end

    unless Program.complete?(Program.to_text(lines)), do: Mix.raise("#{file}: no closing % line")

    with {:error, n} <- Program.check_lines(lines),
         do: Mix.raise("#{file}: line #{n} holds a control character")

    line = opts[:line] || 1

    case Vws.Codecs.NCModal.restart(lines, line) do
      {:ok, preamble, lines} ->
        if line > 1, do: show_restart("#{name} (#{file})", line, preamble, lines)
        {name, Program.to_text(lines)}

      {:error, words} ->
        refuse(name, words)
    end
  end

  defp program([], opts) do
    name =
      case Vws.CEC.Library.name(opts[:program] || usage()) do
        {:ok, name} ->
          if String.ends_with?(name, ".PRO"),
            do: name,
            else: Mix.raise("#{name}: only a part program (nnnnnn.PRO) is drip-fed")

        {:error, :bad_name} ->
          Mix.raise("#{opts[:program]}: not a program name (nnnnnn.PRO, 4711 or O4711)")
      end

    id = opts[:id] || System.get_env("VWS_ID") || "VWS"
    Mix.Task.run("app.config")
    lib = {:dir, opts[:library] || Vws.Ops.DataDir.library_dir(id, :default)}
    line = opts[:line] || 1

    case Vws.Partitions.Monarch.restart(lib, name, opts[:version] || :latest, line) do
      {:ok, lines, version, preamble} ->
        what = "#{name} version #{version}"

        if line > 1,
          do: show_restart(what, line, preamble, lines),
          else: Mix.shell().info("#{what} from the library")

        {name, Program.to_text(lines)}

      {:error, words} ->
        refuse(name, words)
    end
  end

  defp program(_rest, _opts), do: usage()

  defp usage,
    do:
      Mix.raise(
        "usage: mix vws.drip_feed FILE | --program NAME [--version V] [--line K] " <>
          "[--ge2000 ENDPOINT] (see mix help vws.drip_feed)"
      )

  # the preamble, shown before a byte is sent: the program's head, the comment, the preamble
  defp show_restart(what, line, preamble, lines) do
    head = Enum.take_while(lines, &(&1 != "(RESTART AT LINE #{line})"))

    Mix.shell().info(
      "#{what} restarted at line #{line}; sent before it, restoring the modal state of lines " <>
        "1-#{line - 1}:"
    )

    for l <- head ++ ["(RESTART AT LINE #{line})" | preamble], do: Mix.shell().info("  " <> l)
  end

  defp refuse(name, words) do
    Mix.shell().error("#{name}: ERROR #{words} (nothing sent)")
    exit({:shutdown, 1})
  end

  defp simulated(opts, max_text) do
    sim_opts =
      [pace: opts[:baud] || false, link: [max_text: max_text]] ++
        Keyword.take(opts, [:memory, :feed_rate])

    {:ok, sim} = Vws.Sim.GE2000.start_link(sim_opts)
    {Vws.Sim.GE2000.endpoint(sim), sim}
  end

  defp await_link(_link, 0), do: Mix.raise("the GE-2000's line did not come up")

  defp await_link(link, tries) do
    unless DNC.info(link).state == :idle do
      Process.sleep(100)
      await_link(link, tries - 1)
    end
  end

  # progress once a second until the request is over
  defp follow(task, link) do
    case Task.yield(task, 1_000) do
      {:ok, result} ->
        result

      nil ->
        case DNC.progress(link) do
          %{total_program_bytes: total} = p when is_integer(total) ->
            eta = if p.eta_s, do: "#{p.eta_s} s", else: "unknown"

            Mix.shell().info(
              "  #{p.program_bytes}/#{total} bytes, block #{p.blocks}/#{p.total_blocks}, " <>
                "#{p.chars_per_s} chars/s, ETA #{eta}, #{p.retries} retries"
            )

          _ ->
            :ok
        end

        follow(task, link)
    end
  end

  # the machine runs what is still in its buffer (for at most a minute more)
  defp report_machine(sim, tries \\ 600) do
    case Vws.Sim.GE2000.drip(sim) do
      %{state: state} when state in [:feeding, :draining] and tries > 0 ->
        Process.sleep(100)
        report_machine(sim, tries - 1)

      nil ->
        :ok

      d ->
        Mix.shell().info(
          "simulated GE-2000: received #{d.received} bytes, ran #{d.ran}, buffer #{d.max_fill}/#{d.memory} at most, " <>
            "#{d.underruns} underruns, CRC #{Integer.to_string(d.crc, 16)}, state #{d.state}, " <>
            "SHA-256 #{d.sha256}"
        )
    end
  end
end
