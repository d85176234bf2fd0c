defmodule Vws.ArchitectureTest do
  # The layers of docs/architecture.md, checked on the compiler's own dependency graph
  # (`mix xref graph`): no dependency knot, and no edge the wrong way between the folders of
  # lib/vws/ that draw them.
  use ExUnit.Case, async: true

  @moduletag timeout: 120_000

  # lib/vws/<folder>/ → layer; the files at the top of lib/vws/ are named one by one
  @folders [
    {"lib/vws/codecs/", :codecs},
    {"lib/vws/links/", :links},
    {"lib/vws/cec/", :cec},
    {"lib/vws/partitions/", :partitions},
    {"lib/vws/peers/", :peers},
    {"lib/vws/sim/", :sims},
    {"lib/vws/ops/", :ops},
    {"lib/mix/", :ops}
  ]
  # used by every layer, depending on nothing: the registry names of a workstation's parts,
  # telemetry (with whatever sits beside it, a catalogue of events), log limits, the checking
  # of start options and of command-line flags against a schema
  @shared [
    "lib/vws/names.ex",
    "lib/vws/options.ex",
    "lib/vws/cli_options.ex",
    "lib/vws/telemetry.ex",
    "lib/vws/telemetry/",
    "lib/vws/log_limit.ex"
  ]
  # the node: starts the workstations, a hydraulic controller, the dashboard that
  # config/runtime.exs asks for — above every layer, and nothing depends on it
  @root "lib/vws/application.ex"

  @product [:codecs, :links, :cec, :partitions, :shared]

  # what each layer of the product may depend on besides itself
  @allowed %{
    shared: [],
    codecs: [],
    links: [:codecs, :shared],
    cec: [:codecs, :links, :shared, :partitions],
    partitions: [:codecs, :links, :cec, :shared]
  }

  setup_all do
    %{graph: graph()}
  end

  test "every file of lib/ belongs to a layer", %{graph: graph} do
    loose = for {file, _deps} <- graph, layer(file) == :unplaced, do: file

    assert loose == [],
           "these files sit outside the layers' folders (docs/architecture.md \"Layers\"); " <>
             "move them into one or name them in test/architecture_test.exs:\n  " <>
             Enum.join(loose, "\n  ")
  end

  test "no dependency cycle but a facade and its own implementations", %{graph: graph} do
    # a file may depend on the facade above it in its own folder (`transport/tcp.ex` on
    # `transport.ex`: behaviour callbacks, the connection struct); drop those edges, and no
    # cycle may be left
    g = :digraph.new()

    for {file, deps} <- graph, dep <- deps, not facade_of?(dep, file) do
      :digraph.add_vertex(g, file)
      :digraph.add_vertex(g, dep)
      :digraph.add_edge(g, file, dep)
    end

    knots = :digraph_utils.cyclic_strong_components(g)
    :digraph.delete(g)

    assert knots == [],
           "dependency cycles in lib/ (`mix xref graph --format cycles` shows each):\n" <>
             Enum.map_join(knots, "\n", fn files ->
               "  " <> Enum.join(Enum.sort(files), " <-> ")
             end) <>
             "\nBreak them as docs/architecture.md \"Layers\" says: a name or a callback the " <>
             "lower part owns, data passed down, or an event."
  end

  test "the product never depends on simulators, peers or ops", %{graph: graph} do
    wrong =
      for {file, deps} <- graph,
          layer(file) in @product,
          dep <- deps,
          layer(dep) in [:sims, :peers, :ops, :root],
          do: "  #{file} -> #{dep} (#{layer(dep)})"

    assert wrong == [],
           "the product (codecs, links, CEC core, partitions) calls into simulators, peers " <>
             "(the WC, the hydraulic controller's program) or ops (web, MTConnect, inspect, " <>
             "demo, mix tasks) — it must run without them:\n" <> Enum.join(wrong, "\n")
  end

  test "each layer of the product depends only on the layers below it", %{graph: graph} do
    wrong =
      for {file, deps} <- graph,
          from = layer(file),
          from in @product,
          dep <- deps,
          to = layer(dep),
          to in @product,
          to != from,
          to not in @allowed[from] or (from == :cec and to == :partitions and not starts?(file)),
          do: "  #{file} (#{from}) -> #{dep} (#{to})"

    assert wrong == [],
           "edges against the layers (codecs < links < CEC core < partitions; only " <>
             "lib/vws/cec/workstation.ex, which starts the partitions, may name them; " <>
             "names/telemetry/log_limit depend on nothing):\n" <> Enum.join(wrong, "\n")
  end

  defp starts?(file), do: file == "lib/vws/cec/workstation.ex"

  defp facade_of?(dep, file),
    do:
      String.ends_with?(dep, ".ex") and
        String.starts_with?(file, String.trim_trailing(dep, ".ex") <> "/")

  defp layer(@root), do: :root

  defp layer(file) do
    if Enum.any?(
         @shared,
         &(file == &1 or (String.ends_with?(&1, "/") and String.starts_with?(file, &1)))
       ) do
      :shared
    else
      Enum.find_value(@folders, :unplaced, fn {prefix, layer} ->
        if String.starts_with?(file, prefix), do: layer
      end)
    end
  end

  # `mix xref graph --format plain`: each file of the project, then its direct dependencies
  # (`|-- dep` or `` `-- dep ``, with a label such as "(compile)"), for lib/ only
  defp graph do
    mix = System.find_executable("mix") || flunk("mix is not on the PATH")

    {out, status} =
      System.cmd(mix, ["xref", "graph", "--format", "plain"],
        env: [{"MIX_ENV", "test"}],
        stderr_to_stdout: true
      )

    assert status == 0, "mix xref graph failed:\n" <> out

    {graph, _current} =
      out
      |> String.split("\n", trim: true)
      |> Enum.reduce({%{}, nil}, fn line, {graph, current} ->
        case Regex.run(~r/^(?:\|-- |`-- )(\S+)/, line) do
          [_, dep] -> {Map.update!(graph, current, &[dep | &1]), current}
          nil -> {Map.put_new(graph, String.trim(line), []), String.trim(line)}
        end
      end)

    lib? = &String.starts_with?(&1, "lib/")
    graph = for {file, deps} <- graph, lib?.(file), into: %{}, do: {file, Enum.filter(deps, lib?)}
    assert map_size(graph) > 50, "mix xref graph gave no graph:\n" <> out
    graph
  end
end
