defmodule Vws.Ops.MTConnect.Path do
  @moduledoc """
  The `path=` filter of `/current` and `/sample`: the XPath subset MTConnect clients use, evaluated
  over the probe document's elements (`MTConnectDevices/Devices/Device/…/Components/…/DataItems/
  DataItem`). A path selects elements; the data items selected are those elements' `DataItem`s
  and every `DataItem` below them — as the reference agent does. Pure.

  The subset: absolute steps `/` and descendant steps `//`, an element name or `*` per step,
  predicates `[@attr="value"]` or `[@attr='value']` (several, or joined by `and` / `or`, or
  `[@attr]` for "has it"), and unions `a|b`. Anything else — functions, axes, positions — is a
  syntax error (`INVALID_PATH`), never ignored.

      iex> tree = Vws.Ops.MTConnect.Path.tree([Vws.Ops.MTConnect.Model.device("VWS")])
      iex> {:ok, ids} = Vws.Ops.MTConnect.Path.select(~s(//Chuck[@name="vise"]//DataItem[@type="CHUCK_STATE"]), tree)
      iex> MapSet.to_list(ids)
      ["ws_VWS_vise_state"]
      iex> Vws.Ops.MTConnect.Path.select("//DataItem[position()=1]", tree)
      {:error, "unsupported at 'position()=1]'"}
  """

  alias Vws.Ops.MTConnect.Model

  @typedoc "An element of the probe document: name, attributes, children, its data item id if one."
  @type node_ :: %{
          name: String.t(),
          attrs: %{String.t() => String.t()},
          children: [node_],
          id: String.t() | nil
        }

  @doc "The probe document's element tree for `devices` (the agent's device first, if given)."
  @spec tree([Model.device()]) :: node_
  def tree(devices) do
    el("MTConnectDevices", %{}, [el("Devices", %{}, Enum.map(devices, &device/1))])
  end

  defp device(d) do
    el(
      Map.get(d, :kind, "Device"),
      %{"id" => d.id, "name" => d.name, "uuid" => d.uuid},
      contents(d)
    )
  end

  defp component(c), do: el(c.type, %{"id" => c.id, "name" => c.name}, contents(c))

  defp contents(c) do
    items =
      for i <- c.items do
        attrs =
          %{"id" => i.id, "type" => i.type, "category" => String.upcase(to_string(i.category))}
          |> put("name", i[:name])
          |> put("subType", i[:sub_type])
          |> put("units", i[:units])

        %{name: "DataItem", attrs: attrs, children: [], id: i.id}
      end

    if(items == [], do: [], else: [el("DataItems", %{}, items)]) ++
      if c.components == [],
        do: [],
        else: [el("Components", %{}, Enum.map(c.components, &component/1))]
  end

  defp put(map, _k, nil), do: map
  defp put(map, k, v), do: Map.put(map, k, v)

  defp el(name, attrs, children), do: %{name: name, attrs: attrs, children: children, id: nil}

  @doc """
  The ids of the data items `path` selects in `tree`: `{:ok, MapSet}` (never empty), or
  `{:error, why}` for a path that cannot be parsed or selects no data item.
  """
  @spec select(String.t(), node_) :: {:ok, MapSet.t()} | {:error, String.t()}
  def select(path, tree) do
    do_select(path, tree)
  rescue
    # whatever this parser did not foresee is a path it cannot read, not a crash of the agent
    e -> {:error, "unreadable (#{Exception.message(e)})"}
  end

  defp do_select(path, tree) do
    with {:ok, alternatives} <- parse(path) do
      ids =
        for steps <- alternatives,
            node <- eval(steps, [tree], true),
            id <- data_items(node),
            into: MapSet.new(),
            do: id

      if MapSet.size(ids) == 0,
        do: {:error, "no data item matches '#{path}'"},
        else: {:ok, ids}
    end
  end

  defp data_items(%{id: id}) when is_binary(id), do: [id]
  defp data_items(%{children: children}), do: Enum.flat_map(children, &data_items/1)

  # The context starts at the document node (whose one child is the root element).
  defp eval([], nodes, _root?), do: nodes

  defp eval([{axis, name, preds} | rest], nodes, root?) do
    candidates =
      case {axis, root?} do
        {:child, true} -> nodes
        {:child, false} -> Enum.flat_map(nodes, & &1.children)
        {:descendant, true} -> Enum.flat_map(nodes, &self_and_descendants/1)
        {:descendant, false} -> Enum.flat_map(nodes, &descendants/1)
      end

    matched =
      candidates
      |> Enum.filter(
        &((name == "*" or &1.name == name) and Enum.all?(preds, fn p -> test(p, &1) end))
      )
      |> Enum.uniq()

    eval(rest, matched, false)
  end

  defp descendants(node), do: Enum.flat_map(node.children, &self_and_descendants/1)
  defp self_and_descendants(node), do: [node | descendants(node)]

  defp test({:eq, attr, value}, node), do: Map.get(node.attrs, attr) == value
  defp test({:has, attr}, node), do: Map.has_key?(node.attrs, attr)
  defp test({:and, a, b}, node), do: test(a, node) and test(b, node)
  defp test({:or, a, b}, node), do: test(a, node) or test(b, node)

  ## Parsing

  @doc false
  def parse(path) when is_binary(path) do
    path = String.trim(path)

    if path == "" do
      {:error, "empty path"}
    else
      path
      |> split_union()
      |> Enum.reduce_while({:ok, []}, fn alt, {:ok, acc} ->
        case steps(String.trim(alt), []) do
          {:ok, steps} -> {:cont, {:ok, acc ++ [steps]}}
          {:error, _} = e -> {:halt, e}
        end
      end)
    end
  end

  # `|` outside quotes and brackets
  defp split_union(text), do: split_union(text, "", [], nil, 0)

  defp split_union("", cur, acc, _q, _d), do: Enum.reverse([cur | acc])

  defp split_union(<<q, rest::binary>>, cur, acc, nil, d) when q in [?", ?'],
    do: split_union(rest, cur <> <<q>>, acc, q, d)

  defp split_union(<<q, rest::binary>>, cur, acc, q, d),
    do: split_union(rest, cur <> <<q>>, acc, nil, d)

  defp split_union(<<?[, rest::binary>>, cur, acc, nil, d),
    do: split_union(rest, cur <> "[", acc, nil, d + 1)

  defp split_union(<<?], rest::binary>>, cur, acc, nil, d),
    do: split_union(rest, cur <> "]", acc, nil, d - 1)

  defp split_union(<<?|, rest::binary>>, cur, acc, nil, 0),
    do: split_union(rest, "", [cur | acc], nil, 0)

  defp split_union(<<c, rest::binary>>, cur, acc, q, d),
    do: split_union(rest, cur <> <<c>>, acc, q, d)

  defp steps("", []), do: {:error, "empty path"}
  defp steps("", acc), do: {:ok, Enum.reverse(acc)}
  defp steps("//" <> rest, acc), do: step(rest, :descendant, acc)
  defp steps("/" <> rest, acc), do: step(rest, :child, acc)
  # a relative path is taken from the document, as the reference agent takes it
  defp steps(rest, []), do: step(rest, :descendant, [])
  defp steps(rest, _acc), do: {:error, "unsupported at '#{rest}'"}

  defp step(text, axis, acc) do
    case Regex.run(~r/^(\*|[A-Za-z_][A-Za-z0-9_.\-]*(?::[A-Za-z_][A-Za-z0-9_.\-]*)?)/, text) do
      [name | _] ->
        rest = binary_part(text, byte_size(name), byte_size(text) - byte_size(name))
        # a namespace prefix (m:Device) is accepted and dropped
        name = name |> String.split(":") |> List.last()

        with {:ok, preds, rest} <- predicates(rest, []) do
          steps(rest, [{axis, name, preds} | acc])
        end

      nil ->
        {:error, "unsupported at '#{text}'"}
    end
  end

  defp predicates("[" <> rest, acc) do
    with {:ok, pred, rest} <- expr(String.trim_leading(rest)),
         "]" <> rest <- String.trim_leading(rest) do
      predicates(rest, [pred | acc])
    else
      {:error, _} = e -> e
      other when is_binary(other) -> {:error, "unsupported at '#{other}'"}
    end
  end

  defp predicates(rest, acc), do: {:ok, Enum.reverse(acc), rest}

  defp expr(text) do
    with {:ok, left, rest} <- term(text) do
      case Regex.run(~r/^\s+(and|or)\s+/, rest) do
        [m, op] ->
          with {:ok, right, rest} <-
                 expr(binary_part(rest, byte_size(m), byte_size(rest) - byte_size(m))) do
            {:ok, {String.to_atom(op), left, right}, rest}
          end

        nil ->
          {:ok, left, rest}
      end
    end
  end

  defp term(text) do
    case Regex.run(~r/^@([A-Za-z_][A-Za-z0-9_]*)\s*(?:=\s*(?:"([^"]*)"|'([^']*)'))?/, text) do
      [m, attr] ->
        {:ok, {:has, attr}, rest_after(text, m)}

      [m, attr, dq] ->
        {:ok, {:eq, attr, dq}, rest_after(text, m)}

      [m, attr, "", sq] ->
        {:ok, {:eq, attr, sq}, rest_after(text, m)}

      nil ->
        {:error, "unsupported at '#{text}'"}
    end
  end

  defp rest_after(text, m), do: binary_part(text, byte_size(m), byte_size(text) - byte_size(m))
end
