defmodule Vws.Peers.HydraulicController.CecPort do
  @moduledoc false
  # Holds the endpoint on which the CEC reaches the controller (its listener), so that the
  # program can restart without the CEC losing it: a port 0 asked for is bound once, here, and
  # stays the same across restarts of the program. It only holds the listener; the program
  # (init routine 1) takes it and accepts on it.
  use GenServer

  alias Vws.Links.Transport

  def start_link(opts),
    do: GenServer.start_link(__MODULE__, opts, name: Keyword.fetch!(opts, :registered_as))

  def listener(server), do: GenServer.call(server, :listener)

  @impl true
  def init(opts) do
    listen = Keyword.fetch!(opts, :listen)

    with :ok <- Vws.Links.Transport.Policy.check_listen(listen, Keyword.fetch!(opts, :allow)),
         {:ok, listener} <- Transport.listen(listen) do
      {:ok, listener}
    else
      {:error, reason} -> {:stop, {:cannot_listen, reason}}
    end
  end

  @impl true
  def handle_call(:listener, _from, listener), do: {:reply, listener, listener}

  @impl true
  def terminate(_reason, listener), do: Transport.close_listener(listener)
end
