defmodule Vws.ArchitectureTest do
  # The layers of docs/architecture.md ("Layers"), checked on the compiler's own dependency graph
  # (`mix xref graph --format plain`): every file in a layer, every edge the right way between
  # the layers, no compile-time dependency that drags others along, no cycle but a facade and its
  # own files. The rules are written on folders, never on a list of today's files; and before any
  # rule runs, the graph read must be the real one (every file of lib/, the edges and labels we
  # know are there), so that no rule can pass on an empty or misread graph.
  use ExUnit.Case, async: true

  @moduletag timeout: 120_000

  # lib/vws/<folder>/ → layer
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
  # the node: starts the workstations, a hydraulic controller, the dashboard that
  # config/runtime.exs asks for — above every layer; only ops (the mix tasks) start it
  @root "lib/vws/application.ex"
  # Every other file at the top of lib/vws/ (and the folder beside one of them) is shared: used
  # by every layer, depending on nothing — the registry names of a workstation's parts,
  # telemetry, log limits, the checking of options and flags.

  @product [:codecs, :links, :cec, :partitions]

  # what each layer may depend on besides itself; the order docs/architecture.md draws
  @allowed %{
    shared: [],
    codecs: [],
    links: [:codecs, :shared],
    # and lib/vws/cec/workstation.ex, which starts them, on :partitions
    cec: [:codecs, :links, :shared],
    partitions: [:codecs, :links, :cec, :shared],
    # above the simulators as drawn, but like the product they run without them
    peers: [:shared | @product],
    sims: [:shared | @product],
    ops: [:root, :sims, :peers, :shared | @product],
    root: [:ops, :sims, :peers, :shared | @product]
  }
  @starts_partitions "lib/vws/cec/workstation.ex"

  # Edges the code has because of what it is (a layer, or one file); if one is not found, the
  # graph was misread (a changed output format, a filter gone wrong), not the code improved.
  @known_edges [
    {"lib/vws/cec/partition.ex", "lib/vws/cec/mailbox.ex"},
    {:partitions, "lib/vws/cec/mailbox.ex"},
    {"lib/vws/cec/workstation.ex", :partitions},
    {:links, :codecs},
    {:cec, :links},
    {:partitions, :cec},
    {:peers, :codecs},
    {:sims, :codecs},
    {:ops, :peers},
    {:ops, :sims}
  ]

  setup_all do
    %{graph: graph()}
  end

  describe "the graph read is the compiler's" do
    test "every file of lib/ is in it, and nothing else of lib/", %{graph: graph} do
      files = MapSet.new(Path.wildcard("lib/**/*.ex"))
      nodes = MapSet.new(for {file, _} <- graph, lib?(file), do: file)

      assert MapSet.size(files) > 0
      assert MapSet.difference(files, nodes) |> Enum.sort() == []
      assert MapSet.difference(nodes, files) |> Enum.sort() == []
    end

    test "the edges we know are there", %{graph: graph} do
      for {from, to} <- @known_edges do
        assert Enum.any?(graph, fn {file, deps} ->
                 is?(file, from) and Enum.any?(deps, fn {dep, _} -> is?(dep, to) end)
               end),
               "no edge found from #{from} to #{to}: the graph was misread"
      end
    end

    test "every behaviour a module of the project takes is a compile edge to its file", %{
      graph: graph
    } do
      # `@behaviour Vws.A.B` makes the file a compile-time dependant of the behaviour's file:
      # read from the compiled modules, found in the graph with its label
      {:ok, modules} = :application.get_key(:vws, :modules)
      source = &Path.relative_to_cwd(to_string(&1.module_info(:compile)[:source]))

      declared =
        for module <- modules,
            behaviour <- Keyword.get_values(module.module_info(:attributes), :behaviour),
            behaviour <- List.wrap(behaviour),
            behaviour in modules,
            source.(module) != source.(behaviour),
            do: {source.(module), source.(behaviour)}

      assert length(declared) >= 10, "fewer behaviours taken than the partitions alone take"

      for {file, behaviour} <- declared do
        assert {behaviour, :compile} in Map.fetch!(graph, file),
               "#{file} takes the behaviour of #{behaviour}: not a compile edge in the graph"
      end
    end
  end

  test "every file of lib/ belongs to a layer", %{graph: graph} do
    loose =
      for {file, deps} <- graph,
          lib?(file),
          path <- [file | Enum.map(deps, &elem(&1, 0))],
          layer(path) == :unplaced,
          uniq: true,
          do: path

    assert loose == [],
           "these files sit outside the layers' folders (docs/architecture.md \"Layers\"), or " <>
             "lib/ depends on them; move them into a layer's folder:\n  " <>
             Enum.join(loose, "\n  ")
  end

  # Issue 26: a file that does more than one thing grows; 900 lines is where we split it (the
  # moduledoc and the doctests count — they are what a reader reads).
  @max_lines 900

  test "no file of lib/ is over #{@max_lines} lines" do
    files = Path.wildcard(Path.join(Path.expand("../lib", __DIR__), "**/*.ex"))
    assert length(files) > 100, "found only #{length(files)} files under lib/"

    long =
      for file <- files,
          lines = file |> File.read!() |> String.split("\n") |> length(),
          lines > @max_lines,
          do: "#{Path.relative_to(file, Path.expand("..", __DIR__))}: #{lines} lines"

    assert long == [], "split these files by what they do:\n  " <> Enum.join(long, "\n  ")
  end

  test "no compile-time dependency drags others along", %{graph: graph} do
    # A compile edge to a file that depends on anything ("compile-connected") recompiles the one
    # file whenever any of those change. What we find must be what `mix xref graph --label
    # compile-connected` finds (test/support/ too), and none of it may be in lib/.
    connected =
      for {file, deps} <- graph,
          {dep, :compile} <- deps,
          Map.get(graph, dep, []) != [],
          do: {file, dep}

    {out, 0} = xref(["--format", "plain", "--label", "compile-connected"])
    by_xref = for {file, deps} <- parse(out), {dep, :compile} <- deps, do: {file, dep}
    assert Enum.sort(connected) == Enum.sort(by_xref)

    in_lib = for {file, dep} <- connected, lib?(file), do: "  #{file} -> #{dep} (compile)"

    assert in_lib == [],
           "compile-connected edges in lib/ (`mix xref graph --label compile-connected`): " <>
             "each file recompiles with everything the other depends on:\n" <>
             Enum.join(in_lib, "\n") <>
             "\nA behaviour goes in a module of its own that depends on nothing " <>
             "(`Vws.CEC.Partition.CommandSet`, `Vws.Links.Transport.Behaviour`); a module " <>
             "attribute that calls or captures (`&M.f/1`) another module at compile time " <>
             "becomes a function, or names the module as data ({M, :f})."
  end

  test "no dependency cycle but a facade and its direct children", %{graph: graph} do
    # A facade lib/vws/x/y.ex and a file directly in its folder, lib/vws/x/y/z.ex, may depend on
    # each other (a behaviour's implementation, a struct, the process behind the API): drop the
    # edges from such a file up to its facade, and no cycle may be left.
    g = :digraph.new()

    for {file, deps} <- graph,
        lib?(file),
        {dep, _label} <- deps,
        lib?(dep),
        not facade_of?(dep, file) do
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

  test "each layer depends only on the layers below it", %{graph: graph} do
    wrong =
      for {file, deps} <- graph,
          lib?(file),
          from = layer(file),
          from != :unplaced,
          {dep, _label} <- deps,
          to = layer(dep),
          to != from,
          to != :unplaced,
          not (to in @allowed[from] or (file == @starts_partitions and to == :partitions)),
          do: "  #{file} (#{from}) -> #{dep} (#{to})"

    assert wrong == [],
           "edges against the layers (docs/architecture.md \"Layers\": ops > peers > sims > " <>
             "partitions > CEC core > links > codecs, peers without sims; the product never " <>
             "depends on sims, peers or ops; only lib/vws/cec/workstation.ex, which starts the partitions, may name " <>
             "them; only ops start the node; the shared files at the top of lib/vws/ and the " <>
             "codecs depend on nothing):\n" <> Enum.join(wrong, "\n")
  end

  describe "the rules themselves" do
    test "layers come from folders" do
      assert layer("lib/vws/codecs/wc/bcc.ex") == :codecs
      assert layer("lib/vws/cec/partition/command_set.ex") == :cec
      assert layer("lib/mix/tasks/vws.serve.ex") == :ops
      assert layer("lib/vws/names.ex") == :shared
      assert layer("lib/vws/telemetry/catalogue.ex") == :shared
      assert layer(@root) == :root
      assert layer("lib/vws/new_folder/thing.ex") == :unplaced
      assert layer("lib/other.ex") == :unplaced
      assert layer("test/support/test_partition.ex") == :unplaced
    end

    test "only a facade's direct children may depend on it in a cycle" do
      assert facade_of?("lib/vws/links/transport.ex", "lib/vws/links/transport/tcp.ex")
      refute facade_of?("lib/vws/links/transport.ex", "lib/vws/links/transport/loopback/pair.ex")
      refute facade_of?("lib/vws/links/transport.ex", "lib/vws/links/transport_test.ex")
      refute facade_of?("lib/vws/links/transport/tcp.ex", "lib/vws/links/transport.ex")
    end
  end

  defp lib?(file), do: String.starts_with?(file, "lib/")

  # `lib/vws/x/y/z.ex` is a direct child of the facade `lib/vws/x/y.ex`
  defp facade_of?(facade, file),
    do: String.ends_with?(facade, ".ex") and Path.dirname(file) == Path.rootname(facade)

  defp is?(file, layer) when is_atom(layer), do: layer(file) == layer
  defp is?(file, path), do: file == path

  defp layer(@root), do: :root

  defp layer(file) do
    case Enum.find(@folders, fn {prefix, _} -> String.starts_with?(file, prefix) end) do
      {_, layer} -> layer
      nil -> if shared?(file), do: :shared, else: :unplaced
    end
  end

  # lib/vws/<name>.ex, or a file under lib/vws/<name>/ beside it
  defp shared?(file) do
    case Path.split(file) do
      ["lib", "vws", top] -> String.ends_with?(top, ".ex")
      ["lib", "vws", folder | _] -> File.exists?(Path.join(["lib", "vws", folder <> ".ex"]))
      _ -> false
    end
  end

  defp xref(args) do
    mix = System.find_executable("mix") || flunk("mix is not on the PATH")

    System.cmd(mix, ["xref", "graph" | args], env: [{"MIX_ENV", "test"}], stderr_to_stdout: true)
  end

  # `mix xref graph --format plain`: each file of the project, then its direct dependencies,
  # `|-- dep` or `` `-- dep ``, with "(compile)" or "(export)" after it, or nothing (runtime):
  # %{file => [{dep, :compile | :export | :runtime}]}
  defp graph do
    {out, status} = xref(["--format", "plain"])
    assert status == 0, "mix xref graph failed:\n" <> out
    parse(out)
  end

  defp parse(out) do
    {graph, _current} =
      out
      |> String.split("\n", trim: true)
      |> Enum.reduce({%{}, nil}, fn line, {graph, current} ->
        case Regex.run(~r/^(?:\|-- |`-- )(\S+)(?: \((compile|export)\))?$/, line) do
          [_, dep] -> {Map.update!(graph, current, &[{dep, :runtime} | &1]), current}
          [_, dep, label] -> {Map.update!(graph, current, &[{dep, label(label)} | &1]), current}
          nil -> {Map.put_new(graph, file_line!(line), []), line}
        end
      end)

    graph
  end

  defp file_line!(line) do
    if line =~ ~r/^[^\s|`]\S*\.exs?$/, do: line, else: flunk("mix xref graph said: " <> line)
  end

  defp label("compile"), do: :compile
  defp label("export"), do: :export
end
