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

  Options:

    * `--ge2000 ENDPOINT` — the machine's DNC line (`tty:…`, `tcp://…`); without it a simulated
      GE-2000 (`Vws.Sim.GE2000`) is started, and its drip-feed figures are printed at the end
    * `--baud N` — pace the simulated machine's line at N Bd (default: unpaced)
    * `--memory N`, `--feed-rate N` — the simulated machine's block buffer (bytes) and the rate it
      runs the program at (characters a second)
    * `--check lrc|crc` — the block check (default crc)
    * `--max-text N` — text bytes per block (default 256)
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
    max_text: :pos_integer
  ]

  @impl true
  def run(args) do
    {opts, rest} = Vws.CLIOptions.parse!(args, @switches, args: true)

    file =
      case rest do
        [file] -> file
        _ -> Mix.raise("usage: mix vws.drip_feed FILE [--ge2000 ENDPOINT] (see mix help)")
      end

    text =
      case File.read(file) do
        {:ok, text} -> text
        {:error, reason} -> Mix.raise("#{file}: #{:file.format_error(reason)}")
      end

    lines = Program.from_text(text)
    text = Program.to_text(lines)

    name =
      case Program.file_name(lines) do
        {:ok, name} -> name
        {:error, why} -> Mix.raise("#{file}: #{why}")
      end

    unless Program.complete?(text), do: Mix.raise("#{file}: no closing % line")

    with {:error, n} <- Program.check_lines(lines),
         do: Mix.raise("#{file}: line #{n} holds a control character")

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
            "#{d.underruns} underruns, CRC #{Integer.to_string(d.crc, 16)}, state #{d.state}"
        )
    end
  end
end
