defmodule Vws.Sim.GE2000 do
  @moduledoc """
  A simulated GE-2000 (Mark Century) VMC controller on its own endpoint, speaking DNC Level 2
  through the same link as the CEC (`Vws.DNC`, role `:ge`: it bids with `ENQ DEL`, ends with
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
  | `RNL` | sends the status report (`Vws.DNC.Report`): `STATE=IDLE;PROG=001234;ALARM=0` |
  | `RNF` | sends the directory, `nnnnnn.PRO bbbbbb cccc` per file: size and CRC-16/ARC (`Vws.DNC.Report.directory/1`) |

  The alarm number (decision, for the simulator) is the outcome of the last DNC command or
  cycle start: 0 none, 1 no such file, 2 program without program number, 3 refused while the
  machine is active, 4 cycle start without a selected program, 5 operation not supported,
  6 bad file name, 7 program incomplete (no closing `%`: the transmission was cut short).

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
    * `:allow` — who may connect (`Vws.Transport.Policy`; default loopback only)
    * `:pace` — `false` (default), `true` (4 800 Bd, the seed's line) or a baud rate: the
      simulator then paces the line like the real serial link (see `Vws.DNC`, option `:pace`)
    * `:link` — further `Vws.DNC` options (limits, `max_text`)

  ## Faults (`set_fault/2`, at run time)

  `:nak_once_per_block`, `:drop_replies`, `{:wack, n}`, `:corrupt`, `:silent` (see
  `Vws.DNC.set_fault/2`), `:bid_contention` (at the CEC's next bid the GE-2000 bids at the same
  moment, wins, and sends its status report unsolicited), `{:file_as, fun}` (a program received
  whole is filed as `fun.(text)`: a machine that keeps other bytes than it was sent, as a damage
  the block check missed would leave; `:none` ends it too) and `:none`.

      iex> {:ok, sim} = Vws.Sim.GE2000.start_link(programs: %{"000001.PRO" => "O1\\nM30\\n"})
      iex> Vws.Sim.GE2000.endpoint(sim) =~ ~r/^tcp:\\/\\/127.0.0.1:\\d+$/
      true
      iex> Vws.Sim.GE2000.directory(sim)
      ["000001.PRO"]
  """
  use GenServer
  require Logger

  alias Vws.DNC
  alias Vws.DNC.{Frame, Program, Report}
  alias Vws.DNC.Frame.Command

  @default_baud 4800
  @alarms %{
    none: 0,
    no_file: 1,
    no_program_number: 2,
    active: 3,
    nothing_selected: 4,
    unsupported: 5,
    bad_name: 6,
    incomplete: 7
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

  @doc "The simulator's DNC link process."
  @spec link(GenServer.server()) :: pid
  def link(sim), do: GenServer.call(sim, :link)

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
  The machine's state: `%{state, selected, alarm, directory, cycles, downloads}` — `cycles` the
  cycles started, `downloads` the part programs received and filed (`SNS`/`SCS`), so a test can
  count what the machine was made to do.
  """
  @spec state(GenServer.server()) :: map
  def state(sim), do: GenServer.call(sim, :state)

  @doc "The file names in the program directory, sorted."
  @spec directory(GenServer.server()) :: [String.t()]
  def directory(sim), do: state(sim).directory

  @doc "The text of a file, or nil."
  @spec program(GenServer.server(), String.t()) :: binary | nil
  def program(sim, name), do: GenServer.call(sim, {:program, name})

  @doc "Stores a file in the directory, as if loaded at the control panel."
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

    link_opts = Keyword.merge(Keyword.get(opts, :link, []), role: :ge, owner: self(), pace: baud)

    s = %{
      endpoint: Keyword.get(opts, :endpoint, "tcp://127.0.0.1:0"),
      allow: Vws.Transport.Policy.parse_allow!(Keyword.get(opts, :allow)),
      bound: nil,
      listener: nil,
      acceptor: nil,
      link_opts: link_opts,
      link: nil,
      max_text: Keyword.get(link_opts, :max_text, 256),
      programs: Keyword.get(opts, :programs, %{}),
      offsets: Keyword.get_lazy(opts, :offsets, &default_offsets/0),
      selected: nil,
      active: false,
      alarm: 0,
      cycles: 0,
      downloads: 0,
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
    endpoint = Vws.Endpoint.parse!(s.endpoint)

    if endpoint.kind == :tty do
      {:ok, link} = DNC.start_link(Keyword.put(s.link_opts, :endpoint, s.endpoint))
      {:noreply, %{s | link: link, bound: s.endpoint}}
    else
      {:ok, link} = DNC.start_link(s.link_opts)

      case Vws.Transport.listen(endpoint) do
        {:ok, listener} ->
          allow = s.allow
          acceptor = spawn_link(fn -> accept_loop(listener, link, allow) end)
          bound = to_string(Vws.Transport.listener_endpoint(listener))
          Logger.info("GE-2000 simulator listening on #{bound}")
          {:noreply, %{s | link: link, listener: listener, acceptor: acceptor, bound: bound}}

        {:error, reason} ->
          {:stop, {:cannot_listen, s.endpoint, reason}, s}
      end
    end
  end

  # A new connection takes over from the previous one, like a cable plugged in again.
  # Only an allowed peer (default loopback, `Vws.Transport.Policy`) is plugged in.
  defp accept_loop(listener, link, allow) do
    case Vws.Transport.accept(listener, :infinity) do
      {:ok, conn} ->
        with {:ok, ip} <- Vws.Transport.peer_address(conn),
             false <- Vws.Transport.Policy.allowed?(allow, ip) do
          Logger.warning("GE-2000 simulator refused #{Vws.Transport.peer(conn)}: not allowed")
          Vws.Transport.close(conn)
        else
          _ -> attach(link, conn)
        end

        accept_loop(listener, link, allow)

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

  def handle_call({:set_fault, {:file_as, fun}}, _from, s) when is_function(fun, 1),
    do: {:reply, :ok, %{s | file_as: fun}}

  def handle_call({:set_fault, :none}, _from, s),
    do: {:reply, DNC.set_fault(s.link, :none), %{s | file_as: nil}}

  def handle_call({:set_fault, :bid_contention}, _from, s) do
    {:reply, DNC.set_fault(s.link, {:bid_contention, [Report.status(report(s))]}), s}
  end

  def handle_call({:set_fault, fault}, _from, s), do: {:reply, DNC.set_fault(s.link, fault), s}

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
       downloads: s.downloads
     }, s}
  end

  def handle_call({:program, name}, _from, s), do: {:reply, Map.get(s.programs, name), s}

  def handle_call({:put_program, name, text}, _from, s),
    do: {:reply, :ok, %{s | programs: Map.put(s.programs, name, text)}}

  @impl true
  def handle_cast({:cycle_start_input, true}, s), do: {:noreply, start_cycle(s)}
  def handle_cast({:cycle_start_input, false}, s), do: {:noreply, s}

  @impl true
  def handle_info({:dnc, link, {:received, command, blocks}}, %{link: link} = s) do
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

  def handle_info({:dnc, link, {:request, ref, command, _blocks}}, %{link: link} = s) do
    {text, s} = requested(command, s)
    blocks = Frame.split_text(text, s.max_text)

    case DNC.answer(link, ref, blocks) do
      :ok -> :ok
      error -> Logger.warning("GE-2000 simulator could not answer: #{inspect(error)}")
    end

    {:noreply, s}
  end

  def handle_info({:dnc, _link, event}, s) do
    Logger.debug("GE-2000 simulator: link event #{inspect(event, limit: 5)}")
    {:noreply, s}
  end

  def handle_info({:cycle_end, n}, %{cycles: n} = s), do: {:noreply, end_cycle_now(s)}
  def handle_info({:cycle_end, _earlier}, s), do: {:noreply, s}

  def handle_info({:EXIT, pid, reason}, s) when pid in [s.link, s.acceptor] do
    {:stop, reason, s}
  end

  def handle_info(msg, s) do
    Logger.debug("GE-2000 simulator ignored #{inspect(msg, limit: 5)}")
    {:noreply, s}
  end

  @impl true
  def terminate(_reason, s) do
    if s.listener, do: Vws.Transport.close_listener(s.listener)
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

  defp store(s, name, text) do
    Logger.info("GE-2000 simulator stored #{name} (#{byte_size(text)} bytes)")
    %{alarm(s, :none) | programs: Map.put(s.programs, name, text), downloads: s.downloads + 1}
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

  defp file_name(name) do
    name = String.trim(name)

    cond do
      name =~ ~r/^\d{6}\.(PRO|GSU)$/ -> {:ok, name}
      name =~ ~r/^\d{6}$/ -> {:ok, name <> ".PRO"}
      true -> {:error, :bad_name}
    end
  end

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

  defp report(s) do
    %{
      state: if(s.active, do: :active, else: :idle),
      program: s.selected || "000000",
      alarm: s.alarm
    }
  end

  defp alarm(s, name), do: %{s | alarm: Map.fetch!(@alarms, name)}

  defp plant(%{plant: nil}, _event), do: :ok

  defp plant(%{plant: fun}, event) do
    fun.(event)
  rescue
    e -> Logger.error("GE-2000 simulator: plant callback failed: #{Exception.message(e)}")
  end
end
