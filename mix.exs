defmodule Vws.MixProject do
  use Mix.Project

  def project do
    [
      app: :vws,
      version: "0.1.0",
      elixir: "~> 1.14",
      elixirc_paths: elixirc_paths(Mix.env()),
      start_permanent: Mix.env() == :prod,
      deps: [],
      # PropEr comes from Debian's erlang-proper, not from hex: it is on the code path, not a dep
      xref: [exclude: [:proper, :proper_types, :proper_statem, :proper_gen]],
      releases: [vws: [include_executables_for: [:unix], steps: [:assemble, &drop_cookie/1]]]
    ]
  end

  # The node's cookie is made per installation on first start (rel/env.sh.eex), never shipped:
  # the cookie mix writes into the build output would be the same, world-readable, everywhere.
  defp drop_cookie(release) do
    File.rm!(Path.join([release.path, "releases", "COOKIE"]))
    release
  end

  def application do
    [
      extra_applications: [:logger, :runtime_tools, :inets, :crypto],
      mod: {Vws.Application, []}
    ]
  end

  defp elixirc_paths(:test), do: ["lib", "test/support"]
  defp elixirc_paths(_), do: ["lib"]
end
