defmodule Mix.Tasks.Vws.Wc do
  @shortdoc "Drives a live VWS controller as its workstation controller (one command, a script)"
  @moduledoc """
  A workstation controller on the command line (`Vws.Peers.WC.CLI`): sends one status, one command,
  one raw string or a whole cycle script to a running controller's WC link and exits with a
  status — 0 success, 1 the controller said no (`ERROR …`), 2 usage or no controller.

      mix vws.wc --status ROBOT_CMD
      mix vws.wc --endpoint tcp://127.0.0.1:7070 --command 'F OPEN'
      mix vws.wc --script priv/sims/machining_cycle.vws
      mix vws.wc --send '*0001*S0001ROBOT_CMD*'     # the BCC is added

  The release's equivalent is `bin/vws-wc` with the same options. See `Vws.Peers.WC.CLI` for every
  option.
  """
  use Mix.Task

  @impl true
  def run(args) do
    # the configuration and the code, not the application: this is a client, not a workstation
    Mix.Task.run("app.config")

    case Vws.Peers.WC.CLI.main(args) do
      0 -> :ok
      status -> exit({:shutdown, status})
    end
  end
end
