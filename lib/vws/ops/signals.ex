defmodule Vws.Ops.Signals do
  @moduledoc """
  How a node running VWS answers the OS's signals (installed by `Vws.Application`):

    * **SIGTERM** (`kill PID`, `systemctl stop`, a container's stop) and **SIGQUIT** (Ctrl-C in
      a terminal the node has taken, see below; else Ctrl-\\) stop the node cleanly, as `System.stop/0` does: the web server, then every
      workstation (SUN_COMM, the partitions, the device links), then the equipment started
      beside them (e.g. a simulated floor), each in order, and the node exits with status 0.
      The BEAM's own handler does this for SIGTERM, but halts at once on SIGQUIT, with nothing
      stopped in order.
    * **SIGUSR1** halts with a crash dump, as the BEAM's own handler does.
    * **SIGINT** cannot be handled from Erlang (OTP 25's `:os.set_signal/2` refuses it): the
      BEAM opens its BREAK menu, and while it is open every scheduler stands still — no WC
      reply, no HTTP answer, DAQ #1 not polled. So the foreground commands (`mix vws.serve`,
      `mix vws.demo`, `mix vws.hydraulic`, `mix vws.drip_feed`, `iex -S mix …`, a release's
      `bin/vws start` in a terminal) call `ctrl_c_stops/0`: while they run, their terminal sends
      SIGQUIT for Ctrl-C instead of SIGINT, so **one Ctrl-C stops the node in order** (Ctrl-\\
      is then an ordinary key). Only when the node leads the terminal's foreground job — a
      command a user's shell started — is the terminal taken: a command inside a script shares
      its job with the script's shell, which SIGQUIT would end. The terminal's settings come
      back when the application stops or the script ends, and, if the node is killed
      (`kill -9`), when its watcher sees it gone. `VWS_CTRL_C=break` keeps the BEAM's BREAK
      menu.

  `uninstall/0` (called when the application stops) gives the signals back to the BEAM.
  """
  @behaviour :gen_event

  require Logger

  @server :erl_signal_server

  @doc "Makes SIGTERM and SIGQUIT stop the node cleanly (idempotent)."
  @spec install() :: :ok
  def install do
    if __MODULE__ not in :gen_event.which_handlers(@server) do
      :ok = :gen_event.swap_handler(@server, {:erl_signal_handler, []}, {__MODULE__, []})
    end

    :ok = :os.set_signal(:sigquit, :handle)
    :ok = :os.set_signal(:sigterm, :handle)
  end

  @doc "Gives the signals back to the BEAM's own handler (and the terminal its own settings)."
  @spec uninstall() :: :ok
  def uninstall do
    ctrl_c_release()

    if __MODULE__ in :gen_event.which_handlers(@server) do
      :gen_event.swap_handler(@server, {__MODULE__, []}, {:erl_signal_handler, []})
      :os.set_signal(:sigquit, :default)
    end

    :ok
  end

  ## Ctrl-C

  # Run by `sh` beside the node: when the node's standard input is its terminal and the node leads
  # that terminal's foreground process group — a job a user's shell started, not a pipe, a
  # service, a background job, nor a command inside a script (whose shell, in the same group,
  # SIGQUIT would end) —, Ctrl-C is made the terminal's QUIT character and INTR is undefined; then
  # it waits for its standard input (a pipe from the node) to close — the node exited, in order
  # or killed — and puts the terminal's settings back. It ignores the terminal's signals
  # itself (it may be in the foreground group), and SIGTTOU to change the terminal from outside it.
  @ctrl_c_script ~S"""
  trap '' INT QUIT TSTP TTOU HUP
  pid=$1
  tty=$(readlink "/proc/$pid/fd/0" 2>/dev/null) || { echo no; exit 0; }
  case "$tty" in /dev/pts/* | /dev/tty*) ;; *) echo no; exit 0 ;; esac
  stat=$(cat "/proc/$pid/stat" 2>/dev/null) || { echo no; exit 0; }
  set -- ${stat##*) }
  [ "$pid" = "$3" ] && [ "$3" = "$6" ] || { echo no; exit 0; }
  saved=$(stty -g < "$tty" 2>/dev/null) || { echo no; exit 0; }
  stty intr undef quit '^C' < "$tty" 2>/dev/null || { echo no; exit 0; }
  echo yes
  while read -r line; do [ "$line" = restore ] && break; done
  stty "$saved" < "$tty" 2>/dev/null
  echo restored
  """

  @ctrl_c __MODULE__.CtrlC

  @doc """
  Makes one Ctrl-C in this node's terminal stop it in order (as SIGQUIT does), for as long as
  the node runs — when its standard input is a terminal and it runs in the foreground there.
  Returns whether Ctrl-C now does so. `VWS_CTRL_C=break` leaves the BEAM's BREAK menu.
  Idempotent.
  """
  @spec ctrl_c_stops() :: boolean
  def ctrl_c_stops do
    cond do
      System.get_env("VWS_CTRL_C") == "break" -> false
      Process.whereis(@ctrl_c) != nil -> ctrl_c_mapped?()
      sh = System.find_executable("sh") -> start_ctrl_c(sh)
      true -> false
    end
  end

  @doc "Whether Ctrl-C stops the node in order now (`ctrl_c_stops/0` took the terminal)."
  @spec ctrl_c_mapped?() :: boolean
  def ctrl_c_mapped?, do: :persistent_term.get({__MODULE__, :ctrl_c}, false)

  # The watcher's port is owned by a process of its own, linked to nothing: it lives until the
  # node ends (the mix task's process ends under `iex -S mix vws.serve`).
  defp start_ctrl_c(sh) do
    caller = self()
    ref = make_ref()

    pid =
      spawn(fn ->
        port =
          Port.open({:spawn_executable, sh}, [
            :binary,
            :exit_status,
            {:line, 64},
            args: ["-c", @ctrl_c_script, "vws-ctrl-c", System.pid()]
          ])

        answer =
          receive do
            {^port, {:data, {:eol, "yes"}}} -> true
            {^port, _} -> false
          after
            5_000 -> false
          end

        :persistent_term.put({__MODULE__, :ctrl_c}, answer)
        send(caller, {ref, answer})
        # a mix task or script that ends (elixir halts): the terminal back first
        if answer, do: System.at_exit(fn _ -> ctrl_c_release() end)
        ctrl_c_loop(port)
      end)

    try do
      Process.register(pid, @ctrl_c)
    rescue
      ArgumentError -> :ok
    end

    receive do
      {^ref, answer} -> answer
    after
      6_000 -> false
    end
  end

  defp ctrl_c_loop(port) do
    receive do
      {^port, {:exit_status, _}} ->
        :persistent_term.put({__MODULE__, :ctrl_c}, false)

      {:release, from, ref} ->
        # the terminal back before the node goes on stopping (a shell prompting at once after
        # the node's exit must find its own settings), then the watcher is done
        Port.command(port, "restore\n")

        receive do
          {^port, {:data, {:eol, "restored"}}} -> :ok
          {^port, {:exit_status, _}} -> :ok
        after
          2_000 -> :ok
        end

        :persistent_term.put({__MODULE__, :ctrl_c}, false)
        send(from, {ref, :released})
        Port.close(port)

      _ ->
        ctrl_c_loop(port)
    end
  end

  # The terminal's own settings back (the application stops): Ctrl-C is the BEAM's again.
  @doc false
  # The terminal's own settings back now (the application stops, or the mix task's script ends:
  # `elixir` halts without stopping the applications).
  def ctrl_c_release do
    case Process.whereis(@ctrl_c) do
      nil ->
        :ok

      pid ->
        ref = make_ref()
        send(pid, {:release, self(), ref})

        receive do
          {^ref, :released} -> :ok
        after
          2_000 -> :ok
        end
    end
  end

  @impl :gen_event
  def init(_args), do: {:ok, nil}

  @impl :gen_event
  def handle_event(signal, state) when signal in [:sigterm, :sigquit] do
    name = signal |> Atom.to_string() |> String.upcase()

    # not in the signal server's process: it must stay free for the next signal (SIGUSR1's
    # crash dump, a second SIGTERM) whatever the logger or the stop does
    spawn(fn ->
      how = if signal == :sigquit and ctrl_c_mapped?(), do: " (Ctrl-C)", else: ""
      Logger.notice("#{name} received#{how}: stopping (workstations, then their equipment)")
      :init.stop()
    end)

    {:ok, state}
  end

  def handle_event(:sigusr1, _state), do: :erlang.halt(~c"Received SIGUSR1")
  def handle_event(_signal, state), do: {:ok, state}

  @impl :gen_event
  def handle_call(_request, state), do: {:ok, :ok, state}

  @impl :gen_event
  def handle_info(_message, state), do: {:ok, state}

  @impl :gen_event
  def terminate(_args, _state), do: :ok

  @impl :gen_event
  def code_change(_old, state, _extra), do: {:ok, state}
end
