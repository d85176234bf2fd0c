defmodule Vws.Ops.Signals do
  @moduledoc """
  How a node running VWS answers the OS's signals (installed by `Vws.Application`):

    * **SIGTERM** (`kill PID`, `systemctl stop`, a container's stop) and **SIGQUIT** (Ctrl-\\ in
      a terminal) stop the node cleanly, as `System.stop/0` does: the web server, then every
      workstation (SUN_COMM, the partitions, the device links), then the equipment started
      beside them (e.g. a simulated floor), each in order, and the node exits with status 0.
      The BEAM's own handler does this for SIGTERM, but halts at once on SIGQUIT, with nothing
      stopped in order.
    * **SIGUSR1** halts with a crash dump, as the BEAM's own handler does.
    * **SIGINT** (Ctrl-C) cannot be handled from Erlang: the BEAM opens its BREAK menu in a
      terminal (`a` then Enter aborts at once, nothing stopped in order). Use Ctrl-\\ or SIGTERM.

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

  @doc "Gives the signals back to the BEAM's own handler."
  @spec uninstall() :: :ok
  def uninstall do
    if __MODULE__ in :gen_event.which_handlers(@server) do
      :gen_event.swap_handler(@server, {__MODULE__, []}, {:erl_signal_handler, []})
      :os.set_signal(:sigquit, :default)
    end

    :ok
  end

  @impl :gen_event
  def init(_args), do: {:ok, nil}

  @impl :gen_event
  def handle_event(signal, state) when signal in [:sigterm, :sigquit] do
    name = signal |> Atom.to_string() |> String.upcase()

    # not in the signal server's process: it must stay free for the next signal (SIGUSR1's
    # crash dump, a second SIGTERM) whatever the logger or the stop does
    spawn(fn ->
      Logger.notice("#{name} received: stopping (workstations, then their equipment)")
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
