defmodule Mix.Tasks.Vws.Library do
  @shortdoc "The program library: list, show, import, export, diff, release, compare"
  @moduledoc """
  The program library of a workstation (`Vws.CEC.Library`), running or stopped
  (`Vws.Ops.LibraryCLI` has every option):

      mix vws.library list
      mix vws.library show 001234.PRO [--version 2]
      mix vws.library import part.nc [--name 1234]
      mix vws.library export 001234.PRO out.nc [--version 2]
      mix vws.library diff 001234.PRO 1 2
      mix vws.library release 001234.PRO 3    # v3 (from the machine) stored as a released version
      mix vws.library compare [--refresh --endpoint tcp://127.0.0.1:7070]
      mix vws.library --id VWS1 list          # library/VWS1 of the data directory
      mix vws.library --library DIR list      # a library directory itself

  Exit status: 0 done, 1 not found / not stored, 2 usage.
  """
  use Mix.Task

  @impl true
  def run(args) do
    # the configuration and the code, not the application: this works on files
    Mix.Task.run("app.config")

    case Vws.Ops.LibraryCLI.main(args) do
      0 -> :ok
      status -> exit({:shutdown, status})
    end
  end
end
