defmodule Vws.Application do
  @moduledoc false
  use Application

  @impl true
  def start(_type, _args) do
    children = [
      {Registry, keys: :unique, name: Vws.Registry},
      {Registry, keys: :duplicate, name: Vws.Events, partitions: System.schedulers_online()},
      {DynamicSupervisor, name: Vws.WorkstationSupervisor, strategy: :one_for_one}
    ]

    Supervisor.start_link(children, strategy: :one_for_one, name: Vws.Supervisor)
  end
end
