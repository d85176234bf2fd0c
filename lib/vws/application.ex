defmodule Vws.Application do
  @moduledoc false
  use Application

  require Logger

  @impl true
  def start(_type, _args) do
    children =
      [
        {Registry, keys: :unique, name: Vws.Registry},
        {Registry, keys: :duplicate, name: Vws.Events, partitions: System.schedulers_online()},
        {DynamicSupervisor, name: Vws.WorkstationSupervisor, strategy: :one_for_one},
        {DynamicSupervisor, name: Vws.WebSupervisor, strategy: :one_for_one}
      ] ++ configured()

    Supervisor.start_link(children, strategy: :one_for_one, name: Vws.Supervisor)
  end

  # A deployment (the release, with config/runtime.exs) says what to run:
  #   config :vws, :workstation, [id: …, wc: …, partitions: …]   a workstation, started at boot
  #   config :vws, :http, [port: …, bind: …, token: …]            the dashboard and MTConnect agent
  # Nothing is configured in dev and test: there the mix tasks and the tests start what they need.
  defp configured do
    workstation =
      case Application.get_env(:vws, :workstation) do
        nil -> []
        opts -> [%{Vws.Workstation.child_spec(opts) | id: :configured_workstation}]
      end

    http =
      case Application.get_env(:vws, :http) do
        nil -> []
        opts -> [Supervisor.child_spec({Vws.Web, opts}, id: :configured_http)]
      end

    workstation ++ http
  end
end
