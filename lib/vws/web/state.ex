defmodule Vws.Web.State do
  @moduledoc """
  What the dashboard shows, as JSON-ready data (`Vws.JSON`): for every workstation of the node
  (`Vws.Workstation.list/0`) its partitions and command statuses, device statuses, interlocks,
  links and the recent WC dialogue, all read through `Vws.Inspect`; and, when the node is
  connected to others, `cell`: every workstation of the cell with its node and state
  (`Vws.Cell.workstations/1`), else nil. Every value is already text
  or a number, the way a person reads it (`"0007"`, `"ERROR NO LINK TO VAL II"`).
  """

  alias Vws.{Inspect, Mailbox}

  @dialogue_lines 40

  @doc "The dashboard state. Options: `:control` (whether control actions are enabled)."
  @spec build(keyword) :: map
  def build(opts \\ []) do
    %{
      time: DateTime.utc_now() |> DateTime.truncate(:millisecond) |> DateTime.to_iso8601(),
      node: to_string(node()),
      control: Keyword.get(opts, :control, false),
      cell: cell(),
      workstations:
        Vws.Workstation.list()
        |> Task.async_stream(&workstation/1, timeout: 10_000, on_timeout: :kill_task)
        |> Enum.flat_map(fn
          {:ok, shown} -> shown
          {:exit, _} -> []
        end)
    }
  end

  defp cell do
    if Node.list() != [] do
      for w <- Vws.Cell.workstations(2_000) do
        %{
          id: label(w.id),
          node: to_string(w.node),
          state: to_string(w.state),
          wc: Map.get(w, :wc),
          wc_connected: Map.get(w, :wc_connected, false),
          in_flight:
            for {p, {n, :executing}} <- Map.get(w, :commands, %{}) do
              "#{String.upcase(to_string(p))} #{pad4(n)}"
            end
        }
      end
    end
  end

  defp workstation(ws) do
    if Mailbox.exists?(ws), do: [workstation!(ws)], else: []
  rescue
    # stopped while we read it
    ArgumentError -> []
  end

  defp workstation!(ws) do
    snapshot = Inspect.snapshot(ws)

    %{
      id: label(ws),
      partitions: Enum.map(snapshot.partitions, &partition/1),
      devices:
        for d <- snapshot.mailboxes.devices, d.name != "SPARE" or d.value != nil do
          %{
            location: d.location,
            name: d.name,
            value: text(d.value),
            age_ms: if(d.value == nil, do: nil, else: d.age_ms)
          }
        end,
      interlocks:
        for i <- snapshot.interlocks do
          %{
            what: Inspect.label(i.what),
            holder: if(i.holder == nil, do: "-", else: Inspect.label(i.holder)),
            extra:
              if(i.extra == [], do: nil, else: inspect(i.extra, limit: 8, charlists: :as_lists))
          }
        end,
      links: Enum.map(snapshot.links, &link/1),
      wc: wc(snapshot.wc),
      last_sequence: pad4(snapshot.mailboxes.last_sequence),
      events: for({e, n} <- snapshot.mailboxes.events, do: %{event: e, count: n})
    }
  end

  defp partition(r) do
    %{
      name: String.upcase(to_string(r.partition)),
      state: to_string(r.state),
      number: pad4(r.number),
      status: Mailbox.status_word(r.status),
      in_flight: pad4(r.in_flight),
      cmd_in: r.cmd_in,
      current: r.current && "#{pad4(r.current.number)} #{r.current.text}",
      running_ms: r.current && r.current.running_ms,
      done: r.done,
      errors: r.errors,
      restarts: r.restarts,
      link: if(r.link == nil, do: nil, else: inspect(r.link, limit: 5))
    }
  end

  defp link(r) do
    %{
      id: Inspect.label(r.id),
      pid: if(r.pid, do: inspect(r.pid), else: nil),
      state: Inspect.label(r.state),
      info:
        for {k, v} <- Enum.sort(Map.drop(r.info || %{}, [:state])) do
          %{key: to_string(k), value: value(v)}
        end
    }
  end

  defp value(v) when is_binary(v), do: text(v)
  defp value(v) when is_number(v) or is_boolean(v) or is_nil(v), do: v
  defp value(v) when is_atom(v), do: to_string(v)

  defp value(%{} = m) when not is_struct(m),
    do: Enum.map_join(Enum.sort(m), " ", fn {k, v} -> "#{k}=#{short(v)}" end)

  defp value(v), do: inspect(v, limit: 10, printable_limit: 120)

  defp short(v) when is_binary(v), do: text(v)
  defp short(v) when is_atom(v) or is_number(v), do: to_string(v)
  defp short(v), do: inspect(v, limit: 5)

  defp wc(%{info: info, dialogue: dialogue}) do
    base =
      case info do
        %{} = i ->
          %{
            state: if(i.peer, do: "connected", else: "waiting"),
            endpoint: to_string(i.listening || i.endpoint || ""),
            peer: i.peer && to_string(i.peer),
            mode: inspect(i.mode),
            counters: Map.new(i.counters, fn {k, v} -> {k, v} end)
          }

        other ->
          %{state: Inspect.label(other), endpoint: nil, peer: nil, mode: nil, counters: %{}}
      end

    lines =
      for {ms, dir, line} <- Enum.take(dialogue, -@dialogue_lines) do
        %{time: Inspect.clock(ms), dir: to_string(dir), line: text(line)}
      end

    Map.put(base, :dialogue, lines)
  end

  @doc false
  # The text a workstation id is shown (and addressed) by.
  def label(ws), do: Vws.MTConnect.Model.device_name(ws)

  defp text(nil), do: nil
  defp text(v) when is_binary(v), do: if(String.valid?(v), do: v, else: inspect(v))
  defp text(v), do: inspect(v, limit: 20)

  defp pad4(nil), do: nil
  defp pad4(n), do: n |> Integer.to_string() |> String.pad_leading(4, "0")
end
