defmodule Vws.TelemetryCatalogueTest do
  # Vws.Telemetry's catalogue is the list of every event VWS emits: checked on the source (every
  # emission in lib/, its name resolved from the literal it is built from) and on a run (every
  # event of a whole machining cycle, with its measurements and metadata). Not async: the run
  # traces every process of the node.
  use ExUnit.Case, async: false

  import ExUnit.CaptureIO

  @lib Path.expand("../../lib", __DIR__)
  @emitters [:execute, :span]
  @span_suffixes [:start, :stop, :exception]

  describe "on the source" do
    test "every event emitted in lib/ is in the catalogue" do
      {found, unresolved} = scan_lib()

      assert unresolved == [],
             "event names the check cannot resolve to literals (write them as [:vws, …] or pass " <>
               "an atom literal to the helper):\n" <> Enum.join(unresolved, "\n")

      missing =
        for {event, where} <- found,
            event not in Vws.Telemetry.events(),
            do: "#{inspect(event)} at #{where}"

      assert missing == [],
             "emitted but not in Vws.Telemetry's catalogue:\n" <> Enum.join(missing, "\n")

      # the scan does find what is there (a scanner that finds nothing passes everything)
      names = Enum.map(found, &elem(&1, 0))
      assert [:vws, :sun_comm, :wc_refused] in names
      assert [:vws, :dnc, :block_sent] in names
      assert [:vws, :partition, :command, :exception] in names
    end

    test "the catalogue names no event twice, and each as [:vws, component | _]" do
      events = Vws.Telemetry.events()
      assert events == Enum.uniq(events)
      assert Enum.all?(events, &match?([:vws, c, _ | _] when is_atom(c), &1))
    end

    test "the scanner resolves helper arguments and refuses what it cannot read" do
      source = """
      defmodule M do
        def a(x), do: Vws.Telemetry.execute([:vws, :m, :literal], %{}, %{x: x})
        def b, do: emit(:one, 1)
        def c(d), do: d |> emit(:two)
        defp emit(event, _d, _more \\\\ nil), do: Vws.Telemetry.execute([:vws, :m, event], %{}, %{})
        def e(name), do: Vws.Telemetry.execute(name, %{}, %{})
        def f, do: Vws.Telemetry.span([:vws, :m, :job], %{}, fn -> {:ok, %{}} end)
      end
      """

      {found, unresolved} = scan_source(source, "m.ex")

      assert Enum.map(found, &elem(&1, 0)) |> Enum.sort() ==
               Enum.sort([
                 [:vws, :m, :literal],
                 [:vws, :m, :job, :start],
                 [:vws, :m, :job, :stop],
                 [:vws, :m, :job, :exception]
               ])

      # `d |> emit(:two)` gives emit/3 `d` as its event: that emission cannot be read, nor one
      # whose name is no list literal
      assert [emit, e] = Enum.sort(unresolved)
      assert emit =~ ~r/^m\.ex:5: event given as d/
      assert e =~ ~r/^m\.ex:6: not a list literal: name/

      # and the helper given literals only resolves to each of them
      {found, []} =
        scan_source(
          """
          defmodule N do
            def b, do: emit(:one, 1)
            def c(d), do: emit(:two, d, 3)
            defp emit(event, _d, _more \\\\ nil), do: Vws.Telemetry.execute([:vws, :n, event], %{}, %{})
          end
          """,
          "n.ex"
        )

      assert Enum.map(found, &elem(&1, 0)) |> Enum.sort() == [[:vws, :n, :one], [:vws, :n, :two]]
    end
  end

  describe "on a run" do
    test "every event of a whole machining cycle is in the catalogue, with its measurements" do
      id = "catalogue-#{System.unique_integer([:positive])}"
      Code.ensure_loaded!(Vws.Telemetry)
      :erlang.trace_pattern({Vws.Telemetry, :execute, 3}, true, [:local])
      :erlang.trace(:all, true, [:call])
      # VWS_STATUS builds its per-poll event only for a listener (Vws.Telemetry.listened?/1)
      listener = make_ref()

      :ok =
        Vws.Telemetry.attach(listener, [:vws, :vws_status, :poll], fn _, _, _, _ -> :ok end, nil)

      try do
        capture_io(fn ->
          assert {:ok, _summary, floor, client} =
                   Vws.Ops.Demo.run(
                     id: id,
                     wc: "loopback:#{id}",
                     time_scale: 50,
                     poll_interval: 5
                   )

          # the floor is linked to this test's process and ends with it
          _ = floor
          Vws.Peers.WC.Client.close(client)
        end)
      after
        :erlang.trace(:all, false, [:call])
        :erlang.trace_pattern({Vws.Telemetry, :execute, 3}, false, [:local])
        Vws.Telemetry.detach(listener)
      end

      seen = collect(%{})
      catalogue = Map.new(Vws.Telemetry.catalogue(), &{&1.event, &1})

      problems =
        for {event, {measurements, metadata}} <- seen,
            problem = check(catalogue[event], event, measurements, metadata),
            do: problem

      assert problems == [], Enum.join(problems, "\n")
      # a cycle: strings, commands, device polls, DNC blocks, robot messages
      for event <- [
            [:vws, :sun_comm, :string_received],
            [:vws, :partition, :command, :stop],
            [:vws, :vws_status, :poll],
            [:vws, :dnc, :block_sent],
            [:vws, :val, :message]
          ],
          do: assert(Map.has_key?(seen, event), "#{inspect(event)} not seen in the cycle")
    end
  end

  defp collect(seen) do
    receive do
      {:trace, _pid, :call, {Vws.Telemetry, :execute, [event, measurements, metadata]}} ->
        collect(Map.put_new(seen, event, {measurements, metadata}))

      {:trace, _pid, :call, _other} ->
        collect(seen)
    after
      200 -> seen
    end
  end

  defp check(nil, event, _m, _md), do: "#{inspect(event)} is not in the catalogue"

  defp check(entry, event, measurements, metadata) do
    cond do
      Enum.sort(Map.keys(measurements)) != Enum.sort(entry.measurements) ->
        "#{inspect(event)} measures #{inspect(Map.keys(measurements))}, the catalogue says #{inspect(entry.measurements)}"

      Map.keys(metadata) -- entry.metadata != [] ->
        "#{inspect(event)} has metadata #{inspect(Map.keys(metadata) -- entry.metadata)} the catalogue does not list"

      true ->
        nil
    end
  end

  ## The scanner

  defp scan_lib do
    for file <- Path.wildcard(Path.join(@lib, "**/*.ex")),
        Path.basename(file) != "telemetry.ex",
        reduce: {[], []} do
      {found, unresolved} ->
        {f, u} = scan_source(File.read!(file), Path.relative_to(file, Path.dirname(@lib)))
        {found ++ f, unresolved ++ u}
    end
  end

  # {[{event, "file:line"}], ["file:line: why"]}
  #
  # A pure protocol core (no process, no I/O) emits nothing itself: it returns
  # `{:telemetry, name, measurements, metadata}` for its process to emit as `prefix ++ [name]`,
  # and says so with `@telemetry_prefix [:vws, …]` — those tuples are read as emissions (a core
  # that names the whole event, `{:telemetry, [:vws, …], …}`, needs no prefix). The
  # process that emits what its core returned says `@telemetry_relay true`: its emission with a
  # name it was given is checked at the core, not here.
  defp scan_source(source, file) do
    ast = Code.string_to_quoted!(source, file: file)
    defs = defs(ast)
    calls = calls(ast)
    prefix = attribute(ast, :telemetry_prefix)
    relay? = attribute(ast, :telemetry_relay) == true

    {found, unresolved} = scan_defs(defs, calls, prefix, file)
    {found, if(relay?, do: [], else: unresolved)}
  end

  defp attribute(ast, name) do
    {_, value} =
      Macro.prewalk(ast, nil, fn
        {:@, _, [{^name, _, [value]}]} = node, nil -> {node, value}
        node, acc -> {node, acc}
      end)

    value
  end

  defp scan_defs(defs, calls, prefix, file) do
    Enum.reduce(defs, {[], []}, fn {fname, params, body}, acc ->
      body
      |> emissions(prefix)
      |> Enum.reduce(acc, fn {kind, name_ast, line}, {found, unresolved} ->
        where = "#{file}:#{line}"

        case resolve(name_ast, {fname, params}, calls) do
          {:ok, names} ->
            names =
              if kind == :span,
                do: for(n <- names, s <- @span_suffixes, do: n ++ [s]),
                else: names

            {found ++ Enum.map(names, &{&1, where}), unresolved}

          {:error, why} ->
            {found, unresolved ++ ["#{where}: #{why}"]}
        end
      end)
    end)
  end

  # Every def/defp: {name, params, body}.
  defp defs(ast) do
    {_, acc} =
      Macro.prewalk(ast, [], fn
        {kind, _, [head, body]} = node, acc when kind in [:def, :defp] ->
          {name, params} = head(head)
          {node, [{name, params, body} | acc]}

        node, acc ->
          {node, acc}
      end)

    acc
  end

  defp head({:when, _, [call | _]}), do: head(call)
  defp head({name, _, params}) when is_atom(name), do: {name, List.wrap(params)}

  # Every local call outside def heads, pipes undone: {name, [arg]}.
  defp calls(ast) do
    {_, acc} =
      Macro.prewalk(ast, [], fn
        {kind, meta, [_head, body]}, acc when kind in [:def, :defp] ->
          # the head's parameters are no calls
          {{kind, meta, [nil, body]}, acc}

        {:|>, _, [left, {name, _, args}]}, acc when is_atom(name) and is_list(args) ->
          {{:__block__, [], [left | args]}, [{name, [left | args]} | acc]}

        {name, _, args} = node, acc when is_atom(name) and is_list(args) ->
          {node, [{name, args} | acc]}

        node, acc ->
          {node, acc}
      end)

    acc
  end

  defp emissions(body, prefix) do
    {_, acc} =
      Macro.prewalk(body, [], fn
        {{:., meta, [module, fun]}, _, [name | _]} = node, acc when fun in @emitters ->
          if telemetry_module?(module),
            do: {node, [{fun, name, meta[:line]} | acc]},
            else: {node, acc}

        # a core's tuple with the whole name (a list, resolved as an emitter's argument)
        {:{}, meta, [:telemetry, name, _measurements, _metadata]} = node, acc
        when is_list(name) ->
          {node, [{:execute, name, meta[:line]} | acc]}

        {:{}, meta, [:telemetry, name, _measurements, _metadata]} = node, acc
        when is_list(prefix) ->
          {node, [{:execute, prefix ++ [name], meta[:line]} | acc]}

        node, acc ->
          {node, acc}
      end)

    Enum.reverse(acc)
  end

  defp telemetry_module?({:__aliases__, _, [:Vws, :Telemetry]}), do: true
  defp telemetry_module?({:__aliases__, _, [:Telemetry]}), do: true
  defp telemetry_module?(:telemetry), do: true
  defp telemetry_module?(_), do: false

  # The names an event argument takes: a list literal of atoms, where a variable element is a
  # parameter of the enclosing function given as an atom literal at every call of it.
  defp resolve(elements, params, calls) when is_list(elements) do
    Enum.reduce_while(elements, {:ok, [[]]}, fn element, {:ok, prefixes} ->
      case values(element, params, calls) do
        {:ok, atoms} -> {:cont, {:ok, for(p <- prefixes, a <- atoms, do: p ++ [a])}}
        error -> {:halt, error}
      end
    end)
  end

  defp resolve(other, _params, _calls),
    do: {:error, "not a list literal: #{Macro.to_string(other)}"}

  defp values(atom, _params, _calls) when is_atom(atom), do: {:ok, [atom]}

  defp values({var, _, context} = ast, {fname, params}, calls)
       when is_atom(var) and is_atom(context) do
    case Enum.find_index(params, &param?(&1, var)) do
      nil ->
        {:error, "#{Macro.to_string(ast)} is not a parameter of #{fname}"}

      index ->
        default = default(Enum.at(params, index))
        literal_args(calls, fname, index, default, var)
    end
  end

  defp values(other, _params, _calls), do: {:error, "#{Macro.to_string(other)} is not a literal"}

  defp param?({var, _, ctx}, var) when is_atom(ctx), do: true
  defp param?({:\\, _, [{var, _, ctx}, _default]}, var) when is_atom(ctx), do: true
  defp param?(_, _), do: false

  defp default({:\\, _, [_, default]}), do: {:ok, default}
  defp default(_), do: :none

  defp literal_args(calls, fname, index, default, var) do
    case helper_calls(calls, fname, index) do
      [] ->
        {:error, "#{var}: no call of the function found"}

      args ->
        Enum.reduce_while(args, {:ok, []}, fn
          {:ok, atom}, {:ok, acc} when is_atom(atom) ->
            {:cont, {:ok, Enum.uniq(acc ++ [atom])}}

          :default, {:ok, acc} ->
            case default do
              {:ok, atom} when is_atom(atom) -> {:cont, {:ok, Enum.uniq(acc ++ [atom])}}
              _ -> {:halt, {:error, "#{var}: its default is not an atom literal"}}
            end

          {:ok, other}, _acc ->
            {:halt, {:error, "#{var} given as #{Macro.to_string(other)}, not an atom literal"}}
        end)
    end
  end

  # The argument at `index` of every call of the function `name` in the file.
  defp helper_calls(calls, name, index) do
    for {^name, args} <- calls do
      if index < length(args), do: {:ok, Enum.at(args, index)}, else: :default
    end
  end
end
