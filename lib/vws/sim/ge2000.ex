defmodule Vws.Sim.GE2000 do
  @moduledoc """
  A simulated GE-2000 (Mark Century) VMC controller on its own endpoint, speaking DNC Level 2
  through the same link as the CEC (`Vws.Links.DNC`, role `:ge`: it bids with `ENQ DEL`, ends with
  `EOT DEL` and wins contention).

  What it keeps: a program directory (`nnnnnn.PRO`, `nnnnnn.GSU` → text), the selected program,
  a tool-offset table (20 lines `nn ±ddd.dddd` unless given), whether a cycle runs, and an alarm
  number. What it answers (PROTOCOLS.md §2):

  | command | effect |
  |---------|--------|
  | `SNS`/`SCS` + program | stores it as the file named in the command text, else as `nnnnnn.PRO` after its first `O`/`:` word — only a whole program, one ending in a `%` line; otherwise the old file stays (alarm 7) |
  | `SNK` + `nnnnnn[.PRO]` | selects the program for the next cycle start |
  | `SND` + `nnnnnn.PRO`/`.GSU` | deletes the file |
  | `RNS` + file name | sends the file (the selected program without a name); nothing if there is none |
  | `RNO` + `TOFFSET` | sends the tool-offset table |
  | `RNL` | sends the status report (`Vws.Links.DNC.Report`): `STATE=IDLE;PROG=001234;ALARM=0` |
  | `RNF` | sends the directory, `nnnnnn.PRO bbbbbb cccc` per file: size and CRC-16/ARC (`Vws.Links.DNC.Report.directory/1`) |

  The alarm number (decision, for the simulator) is the outcome of the last DNC command or
  cycle start: 0 none, 1 no such file, 2 program without program number, 3 refused while the
  machine is active, 4 cycle start without a selected program, 5 operation not supported,
  6 bad file name, 7 program incomplete (no closing `%`: the transmission was cut short),
  8 program too large (over 999,999 bytes, PROTOCOLS.md §2 "Program size limit": the
  directory's six-digit size field could not say its size; the old file stays), 9 a remote
  request refused by the CEC (its message, on the operator's screen, says why: `state/1`'s
  `messages`).

  The cycle-start button (`cycle_start/1`; `cycle_start_input/2` is the input the DAQ #1 relay
  drives, as on the real machine) runs the
  selected program for `cycle_time` ms: the state is `ACTIVE`, and the optional `plant` function
  is called with `:table_out_of_park` at the start and `:table_in_park` at the end, so a plant
  simulator can move the table without this module depending on it.

  ## Options

    * `:endpoint` — where it listens (`"tcp://127.0.0.1:0"` by default; `loopback:name`), or a
      `tty:` device it opens (one end of a pty pair, a real serial port)
    * `:whole_programs_only` — refuse a `.PRO` that does not end in a `%` line (default true)
    * `:name`, `:programs` (`%{"001234.PRO" => text}`), `:offsets` (`[{line, value}]`),
      `:cycle_time` (5 000 ms), `:plant` (`(event -> any)`)
    * `:allow` — who may connect (`Vws.Links.Transport.Policy`; default loopback only)
    * `:pace` — `false` (default), `true` (4 800 Bd, the seed's line) or a baud rate: the
      simulator then paces the line like the real serial link — a `Vws.Sim.Line` at that baud
      rate (8N1: 10 bits a character) stands in front of its link, where the CEC dials, so
      both directions carry no more than `baud / 10` characters a second (listening endpoints;
      a `tty:` line has the pace of its device)
    * `:link` — further `Vws.Links.DNC` options (limits, `max_text`)
    * `:memory` — the block buffer of a drip feed, bytes (8 192); `:feed_rate` — characters a
      second a drip-fed program runs at (400); `:start_fill` — bytes buffered before the
      program starts to run (half the memory; all of a shorter program); `:tick` — ms between
      the buffer's steps (20)

  ## Drip feed and the operator's programs (ours, docs/dnc-drip-feed.md)

  An `SNE`/`SCE` (download and execute) transmission is run while it arrives: its text blocks go
  into the block buffer and run out of it at `feed_rate`; when the buffer has less than a
  block's room the link answers WACK, and acknowledges once the program has run enough of it
  (`drip/1`). `send_program/2` is the operator sending a program from the control panel to the
  CEC, unasked; `Vws.Sim.GE2000.Panel.request_program/4` the operator asking the CEC for one.

  ## Faults (`set_fault/2`, at run time)

  `:nak_once_per_block`, `:drop_replies`, `{:wack, n}`, `:corrupt`, `:silent` (see
  `Vws.Sim.GE2000.Faults`), `:bid_contention` (at the CEC's next bid the GE-2000 bids at the same
  moment, wins, and sends its status report unsolicited), `{:file_as, fun}` (a program received
  whole is filed as `fun.(text)`: a machine that keeps other bytes than it was sent, as a damage
  the block check missed would leave; `:none` ends it too)) and `:none`.

      iex> {:ok, sim} = Vws.Sim.GE2000.start_link(programs: %{"000001.PRO" => "O1\\nM30\\n"})
      iex> Vws.Sim.GE2000.endpoint(sim) =~ ~r/^tcp:\\/\\/127.0.0.1:\\d+$/
      true
      iex> Vws.Sim.GE2000.directory(sim)
      ["000001.PRO"]
  """
  use GenServer
  require Logger

  alias Vws.Links.DNC
  alias Vws.Links.DNC.{Frame, Program, Report}
  alias Vws.Links.DNC.Frame.Command
  alias Vws.Sim.GE2000.Faults
  alias Vws.Sim.Tap

  @default_baud 4800
  # drip feed: the block buffer, and how fast a program runs out of it (characters a second)
  @default_memory 8_192
  @default_feed_rate 400
  @alarms %{
    none: 0,
    no_file: 1,
    no_program_number: 2,
    active: 3,
    nothing_selected: 4,
    unsupported: 5,
    bad_name: 6,
    incomplete: 7,
    too_large: 8,
    refused: 9
  }

  @doc false
  def child_spec(opts) do
    %{id: Keyword.get(opts, :id, __MODULE__), start: {__MODULE__, :start_link, [opts]}}
  end

  @doc "Starts the simulator (options above)."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts \\ []) do
    case Keyword.get(opts, :name) do
      nil -> GenServer.start_link(__MODULE__, opts)
      name -> GenServer.start_link(__MODULE__, opts, name: name)
    end
  end

  @doc "The endpoint the CEC connects to (with the real port when port 0 was asked)."
  @spec endpoint(GenServer.server()) :: String.t()
  def endpoint(sim), do: GenServer.call(sim, :endpoint)

  @doc false
  # (an operator acts once the CEC's connection has reached the machine's link)
  def connected(link, deadline) do
    if DNC.info(link).state == :disconnected and System.monotonic_time(:millisecond) < deadline do
      Process.sleep(10)
      connected(link, deadline)
    end
  end

  @doc "The simulator's DNC link process."
  @spec link(GenServer.server()) :: pid
  def link(sim), do: GenServer.call(sim, :link)

  @doc """
  The operator at the machine sends program `name` from its directory to the CEC, unasked: the
  GE-2000 bids with `ENQ DEL` and sends `SCS` + `name` and the program's text blocks (ours,
  docs/dnc-drip-feed.md). Returns when the transmission is over: `:ok`, `{:error, :no_file}` or
  the link's error. Waits while the line is busy (the CEC's command goes first).
  """
  @spec send_program(GenServer.server(), String.t(), timeout) :: :ok | {:error, term}
  def send_program(sim, name, timeout \\ 60_000) do
    case GenServer.call(sim, {:program_to_send, name}) do
      {:ok, link, command, blocks} ->
        # an operator sends once the machine's line is connected (the CEC's connection reaches
        # the machine's link through the simulated line a moment after the CEC sees it up)
        connected(link, System.monotonic_time(:millisecond) + min(timeout, 5_000))

        case DNC.request(link, command, blocks, timeout) do
          {:ok, _} -> :ok
          error -> error
        end

      error ->
        error
    end
  end

  @doc """
  The drip feed under way or the last one (nil if none): `%{program, state, received, ran,
  fill, max_fill, memory, feed_rate, blocks, underruns, starved_ms, crc, sha256}` —
  `state` `:feeding` (the program runs while it arrives), `:draining` (all arrived, the buffer
  still runs), `:done`, `:broken` (the feed broke off: the machine stopped, alarm 7);
  `underruns` how often the buffer ran empty while more was to come, `crc` the CRC-16/ARC and
  `sha256` the SHA-256 (lower-case hex) of all text received so far.
  """
  @spec drip(GenServer.server()) :: map | nil
  def drip(sim), do: GenServer.call(sim, :drip)

  @doc "The baud rate its line is paced at, or nil (not paced)."
  @spec baud(GenServer.server()) :: pos_integer | nil
  def baud(sim), do: GenServer.call(sim, :baud)

  @doc "The paced line (`Vws.Sim.Line`) in front of its link, or nil."
  @spec line(GenServer.server()) :: pid | nil
  def line(sim), do: GenServer.call(sim, :line)

  @doc "Makes the simulated controller misbehave (see the moduledoc); `:none` to stop."
  @spec set_fault(GenServer.server(), atom | tuple) :: :ok
  def set_fault(sim, fault), do: GenServer.call(sim, {:set_fault, fault})

  @doc "Presses the cycle-start button: runs the selected program unless one runs already."
  @spec cycle_start(GenServer.server()) :: :ok
  def cycle_start(sim), do: GenServer.call(sim, :cycle_start)

  @doc "Ends the running cycle now, as the program's end would (for an operator or a test)."
  @spec end_cycle(GenServer.server()) :: :ok
  def end_cycle(sim), do: GenServer.call(sim, :end_cycle)

  @doc """
  The machine's state: `%{state, selected, alarm, directory, cycles, downloads, drips, messages}` —
  `cycles` the cycles started, `downloads` the part programs received and filed (`SNS`/`SCS`),
  `drips` the drip feeds started (`SNE`/`SCE`), so a test can count what the machine was made
  to do; `messages` what the CEC said on the operator's screen (a refused remote request),
  newest first.
  """
  @spec state(GenServer.server()) :: map
  def state(sim), do: GenServer.call(sim, :state)

  @doc "The file names in the program directory, sorted."
  @spec directory(GenServer.server()) :: [String.t()]
  def directory(sim), do: state(sim).directory

  @doc "The text of a file, or nil."
  @spec program(GenServer.server(), String.t()) :: binary | nil
  def program(sim, name), do: GenServer.call(sim, {:program, name})

  @doc """
  Stores a file in the directory, as if loaded at the control panel — whatever its size (a
  machine holding one over 999,999 bytes, that its directory cannot describe, is what the CEC's
  reading of a directory line it cannot read is tested with); over DNC it refuses one (alarm 8).
  """
  @spec put_program(GenServer.server(), String.t(), binary) :: :ok
  def put_program(sim, name, text), do: GenServer.call(sim, {:put_program, name, text})

  @doc """
  The cycle-start input, as the DAQ #1 relay wired to it drives it: a closing relay presses the
  button. Asynchronous (a message), so a plant simulator can call it from its own process.
  """
  @spec cycle_start_input(GenServer.server(), boolean) :: :ok
  def cycle_start_input(sim, closed?), do: GenServer.cast(sim, {:cycle_start_input, closed?})

  ## Server

  @impl true
  def init(opts) do
    Process.flag(:trap_exit, true)

    baud =
      case Keyword.get(opts, :pace, false) do
        false -> nil
        nil -> nil
        true -> @default_baud
        baud when is_integer(baud) -> baud
      end

    memory = Keyword.get(opts, :memory, @default_memory)

    link_opts =
      Keyword.merge(Keyword.get(opts, :link, []), role: :ge, owner: self(), receive_buffer: memory)

    s = %{
      endpoint: Keyword.get(opts, :endpoint, "tcp://127.0.0.1:0"),
      allow: Vws.Links.Transport.Policy.parse_allow!(Keyword.get(opts, :allow)),
      bound: nil,
      listener: nil,
      acceptor: nil,
      link_opts: link_opts,
      link: nil,
      # the line end the faults are put in (Vws.Sim.Tap): the link knows nothing of it
      tap: nil,
      baud: baud,
      line: nil,
      memory: memory,
      feed_rate: Keyword.get(opts, :feed_rate, @default_feed_rate),
      start_fill: Keyword.get(opts, :start_fill, div(memory, 2)),
      tick: Keyword.get(opts, :tick, 20),
      drip: nil,
      last_drip: nil,
      max_text: Keyword.get(link_opts, :max_text, 256),
      programs: Keyword.get(opts, :programs, %{}),
      offsets: Keyword.get_lazy(opts, :offsets, &default_offsets/0),
      selected: nil,
      active: false,
      alarm: 0,
      cycles: 0,
      downloads: 0,
      drips: 0,
      # the operator's screen: messages from the CEC, newest first
      messages: [],
      # a remote request under way (Vws.Sim.GE2000.Panel): {caller, request id, file}
      requesting: nil,
      cycle_time: Keyword.get(opts, :cycle_time, 5_000),
      plant: Keyword.get(opts, :plant),
      # false: a machine that files whatever arrived (as the old one did), for tests that show
      # what MONARCH's directory check catches
      whole_programs_only: Keyword.get(opts, :whole_programs_only, true),
      file_as: nil,
      workstation: Vws.Names.id_of(Keyword.get(opts, :name))
    }

    {:ok, s, {:continue, :open}}
  end

  defp default_offsets do
    for n <- 1..20, do: {n, if(rem(n, 2) == 0, do: 1, else: -1) * n * 12.3456}
  end

  @impl true
  def handle_continue(:open, s) do
    endpoint = Vws.Links.Endpoint.parse!(s.endpoint)
    {:ok, tap} = Tap.start_link(owner: self())
    s = %{s | tap: tap}

    if endpoint.kind == :tty do
      # the link dials the tty itself, through the tap
      through_tap = [endpoint: s.endpoint, connect: [transport: Tap, tap: tap]]
      {:ok, link} = DNC.start_link(Keyword.merge(s.link_opts, through_tap))
      {:noreply, %{s | link: link, bound: s.endpoint}}
    else
      {:ok, link} = DNC.start_link(s.link_opts)
      listen = if s.baud, do: "loopback:ge2000-line-#{System.unique_integer([:positive])}"

      case Vws.Links.Transport.listen(listen || endpoint) do
        {:ok, listener} ->
          allow = s.allow
          acceptor = spawn_link(fn -> accept_loop(listener, link, allow, tap) end)
          bound = to_string(Vws.Links.Transport.listener_endpoint(listener))
          s = %{s | link: link, listener: listener, acceptor: acceptor, bound: bound}

          case paced_line(s, bound) do
            {:ok, s} ->
              Logger.info("GE-2000 simulator listening on #{s.bound}")
              {:noreply, s}

            {:error, reason} ->
              {:stop, {:cannot_listen, s.endpoint, reason}, s}
          end

        {:error, reason} ->
          {:stop, {:cannot_listen, s.endpoint, reason}, s}
      end
    end
  end

  # The paced line: the simulator's link listens privately, and a `Vws.Sim.Line` paced at the
  # baud rate listens where the CEC dials, as the serial cable between them.
  defp paced_line(%{baud: nil} = s, _bound), do: {:ok, s}

  defp paced_line(s, bound) do
    line = [listen: s.endpoint, target: bound, faults: [baud: s.baud], reply_slack: 5]

    case Vws.Sim.Line.start_link(line) do
      {:ok, line} -> {:ok, %{s | line: line, bound: to_string(Vws.Sim.Line.endpoint(line))}}
      {:error, reason} -> {:error, reason}
    end
  end

  # A new connection takes over from the previous one, like a cable plugged in again.
  # Only an allowed peer (default loopback, `Vws.Links.Transport.Policy`) is plugged in.
  defp accept_loop(listener, link, allow, tap) do
    case Vws.Links.Transport.accept(listener, :infinity) do
      {:ok, conn} ->
        with {:ok, ip} <- Vws.Links.Transport.peer_address(conn),
             false <- Vws.Links.Transport.Policy.allowed?(allow, ip) do
          Logger.warning(
            "GE-2000 simulator refused #{Vws.Links.Transport.peer(conn)}: not allowed"
          )

          Vws.Links.Transport.close(conn)
        else
          _ -> attach(link, Tap.wrap(conn, tap))
        end

        accept_loop(listener, link, allow, tap)

      {:error, reason} ->
        exit({:accept_failed, reason})
    end
  end

  defp attach(link, conn) do
    case DNC.attach(link, conn) do
      :ok ->
        :ok

      error ->
        Logger.warning("GE-2000 simulator could not take a connection: #{inspect(error)}")
    end
  end

  @impl true
  def handle_call(:endpoint, _from, s), do: {:reply, s.bound, s}
  def handle_call(:link, _from, s), do: {:reply, s.link, s}
  def handle_call(:line, _from, s), do: {:reply, s.line, s}
  def handle_call(:drip, _from, s), do: {:reply, drip_info(s.drip || s.last_drip, s), s}

  def handle_call({:program_to_send, name}, _from, s) do
    with {:ok, file} <- file_name(name),
         {:ok, text} <- Map.fetch(s.programs, file) do
      command = %Command{direction: :send, check: :crc, operation: :part_program, text: file}
      {:reply, {:ok, s.link, command, Frame.split_text(text, s.max_text)}, s}
    else
      _ -> {:reply, {:error, :no_file}, s}
    end
  end

  # A remote request (Vws.Sim.GE2000.Panel): the simulator makes it itself, and its link's reply
  # comes to this process before anything the link receives after it (one sender, in order): the
  # answer is filed before an R command of the CEC's that follows it is answered, and an R command
  # that came first is answered at once — the line is the CEC's until then, and ours goes after.
  def handle_call({:program_request, _command, _timeout}, _from, %{requesting: {_, _, _}} = s),
    do: {:reply, {:error, :busy}, s}

  def handle_call({:program_request, command, timeout}, from, s) do
    request = DNC.send_request(s.link, command, [], timeout)
    {:noreply, %{s | requesting: {from, request, program_file(command.text)}}}
  end

  def handle_call(:baud, _from, s), do: {:reply, s.baud, s}

  def handle_call({:set_fault, {:file_as, fun}}, _from, s) when is_function(fun, 1),
    do: {:reply, :ok, %{s | file_as: fun}}

  def handle_call({:set_fault, :none}, _from, s),
    do: {:reply, Tap.set(s.tap, nil), %{s | file_as: nil}}

  def handle_call({:set_fault, :bid_contention}, _from, s) do
    fault = {:bid_contention, [Report.status(report(s))]}
    {:reply, Tap.set(s.tap, {Faults, Faults.new(fault)}), s}
  end

  def handle_call({:set_fault, fault}, _from, s),
    do: {:reply, Tap.set(s.tap, {Faults, Faults.new(fault)}), s}

  def handle_call(:cycle_start, _from, s), do: {:reply, :ok, start_cycle(s)}
  def handle_call(:end_cycle, _from, s), do: {:reply, :ok, end_cycle_now(s)}

  def handle_call(:state, _from, s) do
    {:reply,
     %{
       state: if(s.active, do: :active, else: :idle),
       selected: s.selected,
       alarm: s.alarm,
       directory: s.programs |> Map.keys() |> Enum.sort(),
       cycles: s.cycles,
       downloads: s.downloads,
       drips: s.drips,
       messages: s.messages
     }, s}
  end

  def handle_call({:program, name}, _from, s), do: {:reply, Map.get(s.programs, name), s}

  def handle_call({:put_program, name, text}, _from, s),
    do: {:reply, :ok, %{s | programs: Map.put(s.programs, name, text)}}

  @impl true
  def handle_cast({:cycle_start_input, true}, s), do: {:noreply, start_cycle(s)}
  def handle_cast({:cycle_start_input, false}, s), do: {:noreply, s}

  @impl true
  # the answer to our remote request (or its link gone) before anything else: filed, or its
  # message shown, or the link's error — and the panel told
  def handle_info(msg, %{requesting: {_, request, _}} = s) do
    case DNC.check_response(msg, request) do
      :no_reply -> info(msg, s)
      answer -> remote_request_answered(answer, s)
    end
  end

  def handle_info(msg, s), do: info(msg, s)

  # the first text block (the command block was 1) starts a new drip feed
  defp info({:dnc, link, {:block, %Command{} = command, 2, text}}, %{link: link} = s),
    do: {:noreply, s |> drip_end(:broken) |> drip_block(command, text)}

  defp info({:dnc, link, {:block, %Command{} = command, _index, text}}, %{link: link} = s),
    do: {:noreply, drip_block(s, command, text)}

  # (a tick of a drip feed that has ended is dropped: one tick chain per feed)
  defp info({:drip_tick, n}, %{drips: n} = s), do: {:noreply, drip_tick(s)}
  defp info({:drip_tick, _ended}, s), do: {:noreply, s}

  defp info(
         {:dnc, link, {:received, %Command{operation: :download_execute}, _}},
         %{link: link} = s
       ),
       do: {:noreply, drip_end(s, :arrived)}

  defp info(
         {:dnc, link, {:aborted, %Command{operation: :download_execute}, _}},
         %{link: link} = s
       ),
       do: {:noreply, drip_end(s, :broken)}

  defp info({:dnc, link, :disconnected}, %{link: link, drip: %{}} = s),
    do: {:noreply, drip_end(s, :broken)}

  defp info({:dnc, link, {:received, command, blocks}}, %{link: link} = s) do
    text = IO.iodata_to_binary(blocks)
    s = received(command, text, s)

    # every S command the machine took (a program stored, selected, deleted), and its outcome
    Vws.Telemetry.execute([:vws, :sim, :ge2000, :command], %{bytes: byte_size(text)}, %{
      workstation: s.workstation,
      operation: command.operation,
      name: String.trim(command.text),
      alarm: s.alarm
    })

    {:noreply, s}
  end

  defp info({:dnc, link, {:request, ref, command, _blocks}}, %{link: link} = s) do
    {text, s} = requested(command, s)
    blocks = Frame.split_text(text, s.max_text)

    case DNC.answer(link, ref, blocks) do
      :ok -> :ok
      error -> Logger.warning("GE-2000 simulator could not answer: #{inspect(error)}")
    end

    {:noreply, s}
  end

  defp info({:dnc, _link, event}, s) do
    Logger.debug("GE-2000 simulator: link event #{inspect(event, limit: 5)}")
    {:noreply, s}
  end

  # the tap took the CEC's bid for ours meeting it (:bid_contention): the link bids now
  defp info({:tap, tap, {:transmit, blocks}}, %{tap: tap} = s) do
    case DNC.transmit(s.link, blocks) do
      :ok -> :ok
      error -> Logger.warning("GE-2000 simulator could not bid: #{inspect(error)}")
    end

    {:noreply, s}
  end

  defp info({:cycle_end, n}, %{cycles: n} = s), do: {:noreply, end_cycle_now(s)}
  defp info({:cycle_end, _earlier}, s), do: {:noreply, s}

  defp info({:EXIT, pid, reason}, s) when pid in [s.link, s.acceptor, s.line, s.tap] do
    {:stop, reason, s}
  end

  defp info(msg, s) do
    Logger.debug("GE-2000 simulator ignored #{inspect(msg, limit: 5)}")
    {:noreply, s}
  end

  @impl true
  def terminate(_reason, s) do
    if s.listener, do: Vws.Links.Transport.close_listener(s.listener)
    :ok
  end

  ## DNC commands

  # S commands: the text has arrived and been acknowledged.
  defp received(%Command{operation: :part_program, text: name}, text, s) do
    name = String.trim(name)

    name =
      cond do
        name =~ ~r/^\d{6}\.(PRO|GSU)$/ -> {:ok, name}
        name == "" -> Program.file_name(text)
        true -> {:error, :bad_name}
      end

    running = s.active && "#{s.selected}.PRO"

    case name do
      {:ok, ^running} ->
        alarm(s, :active)

      {:ok, name} when s.whole_programs_only and binary_part(name, 7, 3) == "PRO" ->
        if Program.complete?(text) do
          store(s, name, text)
        else
          Logger.warning("GE-2000 simulator refused #{name}: no closing %, the old file stays")
          alarm(s, :incomplete)
        end

      {:ok, name} ->
        store(s, name, text)

      {:error, :bad_name} ->
        alarm(s, :bad_name)

      {:error, _} ->
        alarm(s, :no_program_number)
    end
  end

  defp received(%Command{operation: :remote_control, text: name}, _text, s) do
    with {:ok, name} <- file_name(name),
         false <- s.active,
         true <- Map.has_key?(s.programs, name) do
      %{alarm(s, :none) | selected: String.slice(name, 0, 6)}
    else
      {:error, :bad_name} -> alarm(s, :bad_name)
      true -> alarm(s, :active)
      false -> alarm(s, :no_file)
    end
  end

  defp received(%Command{operation: :delete, text: name}, _text, s) do
    with {:ok, name} <- file_name(name),
         {:running, false} <- {:running, s.active and name == "#{s.selected}.PRO"},
         true <- Map.has_key?(s.programs, name) do
      selected = if name == "#{s.selected}.PRO", do: nil, else: s.selected
      %{alarm(s, :none) | programs: Map.delete(s.programs, name), selected: selected}
    else
      {:error, :bad_name} -> alarm(s, :bad_name)
      {:running, true} -> alarm(s, :active)
      false -> alarm(s, :no_file)
    end
  end

  defp received(command, _text, s) do
    Logger.warning("GE-2000 simulator: #{inspect(command)} not supported")
    alarm(s, :unsupported)
  end

  defp store(%{file_as: fun} = s, name, text) when fun != nil do
    store(%{s | file_as: nil}, name, fun.(text)) |> Map.put(:file_as, fun)
  end

  # the directory's size field has six digits: a program it cannot describe is not stored
  # (it would poison every later directory read), the old file stays
  defp store(s, name, text) do
    case Program.check_size(text) do
      :ok ->
        Logger.info("GE-2000 simulator stored #{name} (#{byte_size(text)} bytes)")
        %{alarm(s, :none) | programs: Map.put(s.programs, name, text), downloads: s.downloads + 1}

      {:error, why} ->
        Logger.warning("GE-2000 simulator refused #{name}: #{why}, the old file stays")
        alarm(s, :too_large)
    end
  end

  # R commands: the text to send back.
  defp requested(%Command{operation: :part_program, text: name}, s) do
    name =
      case {String.trim(name), s.selected} do
        {"", nil} -> :none_selected
        {"", selected} -> "#{selected}.PRO"
        {name, _} -> name
      end

    with true <- name != :none_selected || :error,
         {:ok, name} <- file_name(name),
         {:ok, text} <- Map.fetch(s.programs, name) do
      {text, alarm(s, :none)}
    else
      {:error, :bad_name} -> {"", alarm(s, :bad_name)}
      :error -> {"", alarm(s, :no_file)}
    end
  end

  defp requested(%Command{operation: :table}, s), do: {Report.offsets(s.offsets), s}
  defp requested(%Command{operation: :status}, s), do: {Report.status(report(s)), s}

  defp requested(%Command{operation: :directory}, s) do
    {s.programs |> Enum.sort() |> Report.directory(), s}
  end

  defp requested(command, s) do
    Logger.warning("GE-2000 simulator: #{inspect(command)} not supported")
    {"", alarm(s, :unsupported)}
  end

  # The CEC's answer to a remote request: the program, filed as any part program sent to the
  # machine — or its message, shown to the operator.
  defp requested_program(file, text, s) do
    case Regex.run(~r/^\(MSG,([^)\n]*)\)\n?$/, text) do
      [_, words] ->
        Logger.warning("GE-2000 simulator: operator message: #{words}")

        {{:error, {:refused, words}},
         %{alarm(s, :refused) | messages: Enum.take([words | s.messages], 20)}}

      nil ->
        s = received(%Command{operation: :part_program, text: file}, text, s)
        {if(s.alarm == 0, do: :ok, else: {:error, {:alarm, s.alarm}}), s}
    end
  end

  defp remote_request_answered(answer, %{requesting: {from, _request, file}} = s) do
    {told, s} =
      case answer do
        {:ok, blocks} -> requested_program(file, IO.iodata_to_binary(blocks), s)
        error -> {error, s}
      end

    GenServer.reply(from, told)
    {:noreply, %{s | requesting: nil}}
  end

  # the file an R command's text names (nnnnnn.PRO of nnnnnn.PRO/v)
  defp program_file(text), do: text |> String.split("/") |> hd() |> String.trim()

  defp file_name(name) do
    name = String.trim(name)

    cond do
      name =~ ~r/^\d{6}\.(PRO|GSU)$/ -> {:ok, name}
      name =~ ~r/^\d{6}$/ -> {:ok, name <> ".PRO"}
      true -> {:error, :bad_name}
    end
  end

  ## Drip feed (E, download and execute): the block buffer
  #
  # Text blocks of an E transmission arrive into the buffer (`memory` bytes; the link answers
  # WACK once less than a block's room is left, see Vws.Links.DNC.Session) and the program runs out
  # of it at `feed_rate` characters a second, every `tick` ms; what ran is given back to the
  # link as credit. The buffer running empty while more is to come is an underrun (the machine
  # would dwell); the feed broken off stops the machine (alarm 7, program incomplete).

  defp drip_block(%{drip: nil} = s, command, text) do
    Logger.info("GE-2000 simulator: drip feed of #{String.trim(command.text)} started")

    drip = %{
      program: String.trim(command.text),
      state: :feeding,
      received: 0,
      ran: 0,
      fill: 0,
      max_fill: 0,
      blocks: 0,
      underruns: 0,
      starved_ms: 0,
      empty_since: nil,
      owed: 0.0,
      crc: 0,
      sha256: :crypto.hash_init(:sha256),
      tail: "",
      running: false,
      last_tick: now_ms()
    }

    Process.send_after(self(), {:drip_tick, s.drips + 1}, s.tick)
    s = %{alarm(s, :none) | drip: drip, active: true, drips: s.drips + 1}
    drip_block(s, command, text)
  end

  defp drip_block(%{drip: drip} = s, _command, text) do
    fill = drip.fill + byte_size(text)

    drip =
      %{
        drip
        | received: drip.received + byte_size(text),
          fill: fill,
          max_fill: max(drip.max_fill, fill),
          blocks: drip.blocks + 1,
          crc: Vws.Codecs.CRC16.compute(text, drip.crc),
          sha256: :crypto.hash_update(drip.sha256, text),
          tail: text
      }
      |> fed()

    %{s | drip: drip}
  end

  # the buffer got bytes again: an underrun (if any) is over
  defp fed(%{empty_since: nil} = drip), do: drip

  defp fed(drip),
    do: %{drip | empty_since: nil, starved_ms: drip.starved_ms + now_ms() - drip.empty_since}

  defp drip_tick(%{drip: nil} = s), do: s

  # The control buffers before it runs: it starts once `start_fill` bytes (half its memory by
  # default) are in, or the whole program if it is shorter.
  defp drip_tick(%{drip: %{running: false} = drip} = s)
       when drip.fill < s.start_fill and drip.state == :feeding do
    Process.send_after(self(), {:drip_tick, s.drips}, s.tick)
    %{s | drip: %{drip | last_tick: now_ms()}}
  end

  defp drip_tick(%{drip: drip} = s) do
    # the machine moves from its first block on: the plant sees the table leave its park
    unless drip.running, do: plant(s, :table_out_of_park)
    drip = %{drip | running: true}
    now = now_ms()
    owed = drip.owed + s.feed_rate * (now - drip.last_tick) / 1000
    ran = min(drip.fill, trunc(owed))
    owed = if ran == drip.fill, do: 0.0, else: owed - ran
    drip = %{drip | fill: drip.fill - ran, ran: drip.ran + ran, owed: owed, last_tick: now}
    if ran > 0, do: DNC.grant(s.link, ran)

    drip =
      cond do
        drip.fill > 0 or drip.empty_since != nil -> drip
        drip.state == :feeding -> %{drip | empty_since: now, underruns: drip.underruns + 1}
        true -> drip
      end

    if drip.state == :draining and drip.fill == 0 do
      finish_drip(s, drip, :done)
    else
      Process.send_after(self(), {:drip_tick, s.drips}, s.tick)
      %{s | drip: drip}
    end
  end

  defp drip_end(%{drip: nil} = s, _how), do: s

  defp drip_end(%{drip: drip} = s, :broken), do: finish_drip(s, fed(drip), :broken)

  # Whole: the last block ends with the % line, and it is not the tape's leading rewind stop
  # alone (a transmission cut after a first block of just "%" LF ran nothing of the program).
  defp drip_end(%{drip: drip} = s, :arrived) do
    if (String.ends_with?(drip.tail, "%\n") or String.ends_with?(drip.tail, "%")) and
         drip.received > byte_size("%\n") do
      %{s | drip: %{fed(drip) | state: :draining}}
    else
      Logger.warning("GE-2000 simulator: drip feed ended without the closing %: stopped")
      finish_drip(s, fed(drip), :broken)
    end
  end

  defp finish_drip(s, drip, how) do
    Logger.info("GE-2000 simulator: drip feed of #{drip.program} #{how}")

    Vws.Telemetry.execute([:vws, :sim, :ge2000, :drip_feed], %{bytes: drip.received}, %{
      workstation: s.workstation,
      program: drip.program,
      result: how,
      underruns: drip.underruns
    })

    s = if how == :broken, do: alarm(s, :incomplete), else: s
    if drip.running, do: plant(s, :table_in_park)
    %{s | drip: nil, last_drip: %{drip | state: how}, active: false}
  end

  defp drip_info(nil, _s), do: nil

  defp drip_info(drip, s) do
    drip
    |> Map.drop([:owed, :tail, :last_tick, :empty_since, :running])
    |> Map.merge(%{memory: s.memory, feed_rate: s.feed_rate})
    |> Map.put(:sha256, Base.encode16(:crypto.hash_final(drip.sha256), case: :lower))
  end

  defp now_ms, do: System.monotonic_time(:millisecond)

  ## The machine

  defp start_cycle(%{active: true} = s), do: s

  defp start_cycle(s) do
    if s.selected && Map.has_key?(s.programs, "#{s.selected}.PRO") do
      Logger.info("GE-2000 simulator: cycle start, running #{s.selected}")

      Vws.Telemetry.execute([:vws, :sim, :ge2000, :cycle_start], %{count: 1}, %{
        workstation: s.workstation,
        program: s.selected
      })

      plant(s, :table_out_of_park)
      Process.send_after(self(), {:cycle_end, s.cycles + 1}, s.cycle_time)
      %{alarm(s, :none) | active: true, cycles: s.cycles + 1}
    else
      alarm(s, :nothing_selected)
    end
  end

  defp end_cycle_now(%{active: false} = s), do: s

  defp end_cycle_now(s) do
    Logger.info("GE-2000 simulator: cycle of #{s.selected} ended")
    plant(s, :table_in_park)
    %{s | active: false}
  end

  # while a drip feed runs, the program it runs is the machine's program
  defp report(s) do
    %{
      state: if(s.active, do: :active, else: :idle),
      program: drip_number(s.drip) || s.selected || "000000",
      alarm: s.alarm
    }
  end

  defp drip_number(%{program: program}) do
    case Regex.run(~r/^\d{6}/, program) do
      [number] -> number
      nil -> nil
    end
  end

  defp drip_number(nil), do: nil

  defp alarm(s, name), do: %{s | alarm: Map.fetch!(@alarms, name)}

  defp plant(%{plant: nil}, _event), do: :ok

  defp plant(%{plant: fun}, event) do
    fun.(event)
  rescue
    e -> Logger.error("GE-2000 simulator: plant callback failed: #{Exception.message(e)}")
  end
end
