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
      releases: [vws: [include_executables_for: [:unix]]]
    ]
  end

  def application do
    [
      extra_applications: [:logger, :runtime_tools, :inets],
      mod: {Vws.Application, []}
    ]
  end

  defp elixirc_paths(:test), do: ["lib", "test/support"]
  defp elixirc_paths(_), do: ["lib"]
end
