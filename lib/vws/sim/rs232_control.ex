defmodule Vws.Sim.RS232Control do
  @moduledoc """
  A simulated CNC control with a plain RS-232 port under XON/XOFF (the profile `rs232-xonxoff`
  of `Vws.Links.RS232`; docs/serial.md): what most controls in service are, to test the CEC
  against.

  **Its buffer.** Received bytes go into a buffer of `buffer` bytes (default 256), which the
  control empties at `rate` characters a second (default 1 000: it parses and stores, or runs
  a drip-fed program). When the buffer holds `high` bytes or more it
  sends XOFF (DC3); once it is down to `low` (default a quarter) it sends XON (DC1). `high`
  defaults to half the buffer: the other half is for what is in flight when the sender sees the
  XOFF. A byte that
  finds the buffer full is **dropped** and counted (`dropped`, `alarms` gets `:overrun`): a
  sender that ignores XOFF loses bytes, and the program the control keeps is not the one sent.

  **Programs.** What it empties from its buffer is read with the shop's framing
  (`Vws.Links.RS232.Framing`, option `framing`): each whole program is kept under its number
  (`001234.PRO`) and as `last`. `punch/2` sends a kept program back (the operator's PUNCH);
  `punch_after_load: true` does so by itself after each program it keeps, standing in for an
  operator who reads every download back. `ready_dc1: true` sends DC1 when a CEC connects and
  after each program, for a CEC that waits for it.

  **Faults** (`set_fault/2`): `{:flip, n, bit}` flips one bit of the `n`-th byte (0-based) of the
  next program it keeps, as line noise the CEC cannot see — its read-back then differs;
  `:never_xon` holds its XOFF for ever (the CEC must give up in bounded time).

  **Busy at the start** (`busy_until_xoff: true`): it empties nothing until it has said XOFF
  once (or nothing has come for a second: a program smaller than its buffer), as a control busy
  when a transfer begins. A sender on a loaded host may fall behind the line's pace, and a
  control slower than the line then never fills its buffer; with this, a test sees the flow
  control work whatever the sender's pace. (The quiet line was 100 ms: a CI run's sender, held
  up that long on a loaded host, ended the busy start before the buffer was full, and the
  control never said XOFF.)

  Where it is: `listen:` an endpoint (default `tcp://127.0.0.1:0`, one CEC at a time, the newest
  wins) or `tty:` a serial device it opens itself (a pty of a pair, say). `endpoint/1` says where.
  """
  use GenServer
  require Logger

  alias Vws.Links.Transport
  alias Vws.Links.DNC.Program
  alias Vws.Links.RS232.Framing

  @dc1 0x11
  @dc3 0x13
  @tick 10

  @doc "Starts the control (options above)."
  @spec start_link(keyword) :: GenServer.on_start()
  def start_link(opts), do: GenServer.start_link(__MODULE__, opts, Keyword.take(opts, [:name]))

  @doc false
  def child_spec(opts),
    do: %{id: Keyword.get(opts, :id, __MODULE__), start: {__MODULE__, :start_link, [opts]}}

  @doc "The endpoint a CEC connects to (the bound one, for a listener on port 0)."
  @spec endpoint(GenServer.server()) :: String.t()
  def endpoint(sim), do: GenServer.call(sim, :endpoint)

  @doc """
  What it holds and counts: `programs` (name → text), `last`, `dropped`, `max_fill`, `xoffs`,
  `xons`, `alarms`, `connected`.
  """
  @spec info(GenServer.server()) :: map
  def info(sim), do: GenServer.call(sim, :info)

  @doc """
  The operator's PUNCH: sends a kept program (`:last`, or its name) to the CEC;
  `{:error, :not_connected}` while no CEC is connected.
  """
  @spec punch(GenServer.server(), :last | String.t()) ::
          :ok | {:error, :no_such_program | :not_connected}
  def punch(sim, which \\ :last), do: GenServer.call(sim, {:punch, which})

  @doc "Sets a fault (see above), or none with `nil`."
  @spec set_fault(GenServer.server(), term) :: :ok
  def set_fault(sim, fault), do: GenServer.call(sim, {:fault, fault})

  ## Server

  @impl true
  def init(opts) do
    {:ok, framing} = Framing.new(Keyword.get(opts, :framing, []))
    size = Keyword.get(opts, :buffer, 256)

    s = %{
      framing: framing,
      decoder: Framing.decoder(framing),
      size: size,
      high: Keyword.get(opts, :high, div(size, 2)),
      low: Keyword.get(opts, :low, div(size, 4)),
      rate: Keyword.get(opts, :rate, 1_000),
      punch_after_load: Keyword.get(opts, :punch_after_load, false),
      punch_delay: Keyword.get(opts, :punch_delay, 20),
      ready_dc1: Keyword.get(opts, :ready_dc1, false),
      busy_until_xoff: Keyword.get(opts, :busy_until_xoff, false),
      last_rx: nil,
      programs: Keyword.get(opts, :programs, %{}),
      last: nil,
      buffer: <<>>,
      credit: 0.0,
      last_tick: nil,
      xoff: false,
      fault: nil,
      conn: nil,
      listener: nil,
      endpoint: nil,
      tty: Keyword.get(opts, :tty),
      listen: Keyword.get(opts, :listen, "tcp://127.0.0.1:0"),
      dropped: 0,
      max_fill: 0,
      xoffs: 0,
      xons: 0,
      alarms: []
    }

    {:ok, s, {:continue, :open}}
  end

  @impl true
  def handle_continue(:open, %{tty: nil} = s) do
    case Transport.listen(s.listen) do
      {:ok, listener} ->
        Transport.start_acceptor(listener, self(), :accepted)
        endpoint = to_string(Transport.listener_endpoint(listener))
        tick()
        {:noreply, %{s | listener: listener, endpoint: endpoint}}

      {:error, reason} ->
        {:stop, {:cannot_listen, s.listen, reason}}
    end
  end

  def handle_continue(:open, s) do
    send(self(), :open_tty)
    tick()
    {:noreply, %{s | endpoint: s.tty}}
  end

  @impl true
  def handle_call(:endpoint, _from, s), do: {:reply, s.endpoint, s}

  def handle_call(:info, _from, s) do
    info =
      Map.take(s, [:programs, :last, :dropped, :max_fill, :xoffs, :xons, :alarms])
      |> Map.put(:connected, s.conn != nil)
      |> Map.put(:fill, byte_size(s.buffer))

    {:reply, info, s}
  end

  def handle_call({:punch, which}, _from, s) do
    text = if which == :last, do: s.last, else: Map.get(s.programs, which)

    cond do
      s.conn == nil -> {:reply, {:error, :not_connected}, s}
      text == nil -> {:reply, {:error, :no_such_program}, s}
      true -> {:reply, :ok, punch_text(s, text)}
    end
  end

  def handle_call({:fault, fault}, _from, s), do: {:reply, :ok, %{s | fault: fault}}

  @impl true
  def handle_info({:accepted, conn}, s) do
    if s.conn, do: Transport.close(s.conn)
    {:noreply, connected(s, conn)}
  end

  def handle_info(:open_tty, s) do
    case Transport.connect(s.tty) do
      {:ok, conn} ->
        {:noreply, connected(s, conn)}

      {:error, _} ->
        Process.send_after(self(), :open_tty, 100)
        {:noreply, s}
    end
  end

  def handle_info(:tick, s) do
    tick()
    {:noreply, drain(s)}
  end

  def handle_info({:punch_last, text}, s), do: {:noreply, punch_text(s, text)}

  def handle_info(msg, %{conn: conn} = s) when conn != nil do
    case Transport.handle_message(conn, msg) do
      {:data, bytes} ->
        :ok = Transport.activate(conn)
        {:noreply, take(s, bytes)}

      :unknown ->
        {:noreply, s}

      _closed ->
        Transport.close(conn)
        if s.tty, do: Process.send_after(self(), :open_tty, 100)
        {:noreply, %{s | conn: nil, xoff: false}}
    end
  end

  def handle_info(_msg, s), do: {:noreply, s}

  defp connected(s, conn) do
    :ok = Transport.activate(conn)
    s = %{s | conn: conn, xoff: false}
    if s.ready_dc1, do: out(s, <<@dc1>>), else: s
  end

  defp tick, do: Process.send_after(self(), :tick, @tick)

  # ms of a quiet line that end a busy start (busy_until_xoff) before an XOFF
  @busy_quiet 1_000

  ## The buffer: filled by the line, emptied at the control's rate

  # DC1/DC3 from the CEC would pace a punch; this control punches at once and ignores them
  defp take(s, bytes) do
    room = s.size - byte_size(s.buffer)
    kept = binary_part(bytes, 0, min(room, byte_size(bytes)))
    lost = byte_size(bytes) - byte_size(kept)
    buffer = s.buffer <> kept
    now = System.monotonic_time(:millisecond)
    s = %{s | buffer: buffer, max_fill: max(s.max_fill, byte_size(buffer)), last_rx: now}

    s =
      if lost > 0 do
        # said once; `dropped` counts them all
        unless :overrun in s.alarms,
          do: Logger.warning("RS-232 control: buffer overrun, #{lost} bytes dropped")

        alarms = if :overrun in s.alarms, do: s.alarms, else: [:overrun | s.alarms]
        %{s | dropped: s.dropped + lost, alarms: alarms}
      else
        s
      end

    if byte_size(buffer) >= s.high and not s.xoff,
      do: %{out(s, <<@dc3>>) | xoff: true, xoffs: s.xoffs + 1},
      else: s
  end

  # busy at the start (busy_until_xoff): nothing emptied until an XOFF, or a quiet line
  defp drain(%{busy_until_xoff: true, xoffs: 0} = s) do
    quiet? = s.last_rx != nil and System.monotonic_time(:millisecond) - s.last_rx >= @busy_quiet

    if quiet?,
      do: drain(%{s | busy_until_xoff: false}),
      else: %{s | last_tick: System.monotonic_time(:microsecond)}
  end

  # by the time that has passed, not the ticks counted: a late tick must not slow the control
  defp drain(s) do
    now = System.monotonic_time(:microsecond)
    credit = s.credit + s.rate * (now - (s.last_tick || now - @tick * 1000)) / 1_000_000
    s = %{s | last_tick: now}
    n = min(trunc(credit), byte_size(s.buffer))
    <<bytes::binary-size(n), rest::binary>> = s.buffer
    s = %{s | buffer: rest, credit: if(rest == <<>>, do: 0.0, else: credit - n)}
    {events, decoder} = Framing.decode(s.decoder, bytes)
    s = Enum.reduce(events, %{s | decoder: decoder}, &program/2)

    if s.xoff and byte_size(rest) <= s.low and s.fault != :never_xon,
      do: %{out(s, <<@dc1>>) | xoff: false, xons: s.xons + 1},
      else: s
  end

  defp program({:program, text}, s) do
    {text, fault} = flip(text, s.fault)
    s = %{s | fault: fault, last: text}

    s =
      case Program.file_name(Program.from_text(text)) do
        {:ok, name} -> %{s | programs: Map.put(s.programs, name, text)}
        {:error, _} -> s
      end

    if s.punch_after_load, do: Process.send_after(self(), {:punch_last, text}, s.punch_delay)
    if s.ready_dc1, do: out(s, <<@dc1>>), else: s
  end

  defp program({:error, reason}, s) do
    Logger.warning("RS-232 control: a program arrived damaged (#{reason})")
    %{s | alarms: [reason | s.alarms]}
  end

  defp flip(text, {:flip, n, bit}) when n < byte_size(text) do
    <<before::binary-size(n), byte, rest::binary>> = text
    {<<before::binary, Bitwise.bxor(byte, Bitwise.bsl(1, bit)), rest::binary>>, nil}
  end

  defp flip(text, fault), do: {text, fault}

  defp punch_text(s, text), do: out(s, Framing.encode(text, s.framing))

  defp out(%{conn: nil} = s, _bytes), do: s

  defp out(s, bytes) do
    _ = Transport.send(s.conn, bytes)
    s
  end
end
