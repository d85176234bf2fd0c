defmodule Vws.Links.DDCMP.Wire do
  @moduledoc false

  # emits the telemetry its core (Vws.Links.DDCMP.Protocol, @telemetry_prefix) returns
  @telemetry_relay true

  @doc false
  def telemetry_relay?, do: @telemetry_relay
  # What a process that owns a DDCMP line (`Vws.Links.DDCMP.Link`, `Vws.Links.VAL.Connection`,
  # `Vws.Sim.VAL2`) does with the result of a `Vws.Links.DDCMP.Protocol` call: the I/O the pure core
  # leaves out. Frames are encoded and written to the transport as one chunk, telemetry points are
  # emitted with the line's `link`/`workstation` metadata, timers become gen_statem generic
  # timeouts named after them, and the protocol's news (`:up`, `{:data, _}`, `{:down, _}`,
  # `:peer_restarted`) is handed back, in order, for the owner to act on in the same callback.

  require Logger

  alias Vws.Links.DDCMP.Frame
  alias Vws.Links.Transport

  @type meta :: %{link: term, workstation: term}

  @doc false
  # Writes the frames, emits the telemetry; returns the news and the timers to arm, in order,
  # as gen_statem generic timeouts named after them.
  @spec perform([Frame.t()], [Vws.Links.DDCMP.Protocol.event()], Transport.Conn.t() | nil, meta) ::
          {[term], [:gen_statem.action()]}
  def perform(frames, events, conn, meta) do
    {news, timers} = perform_raw(frames, events, conn, meta)

    {news,
     Enum.map(timers, fn
       {name, :cancel} -> {{:timeout, name}, :cancel}
       {name, ms} -> {{:timeout, name}, ms, name}
     end)}
  end

  @doc false
  # The same with the timers as `{name, ms | :cancel}`, for processes that are no gen_statem.
  @spec perform_raw(
          [Frame.t()],
          [Vws.Links.DDCMP.Protocol.event()],
          Transport.Conn.t() | nil,
          meta
        ) ::
          {[term], [{atom, pos_integer | :cancel}]}
  def perform_raw(frames, events, conn, meta) do
    write(conn, frames)

    {news, timers} =
      Enum.reduce(events, {[], []}, fn
        {:telemetry, event, measurements, metadata}, acc ->
          telemetry(meta, event, measurements, metadata)
          acc

        {:timer, name, ms_or_cancel}, {news, timers} ->
          {news, [{name, ms_or_cancel} | timers]}

        other, {news, timers} ->
          {[other | news], timers}
      end)

    {Enum.reverse(news), Enum.reverse(timers)}
  end

  @doc false
  # Arms and cancels timers for a plain process: `armed` maps a timer's name to its reference;
  # it expires as `{:timeout, ref, {:ddcmp, name}}`, to be taken only while `armed[name] == ref`.
  @spec arm(%{atom => reference}, [{atom, pos_integer | :cancel}]) :: %{atom => reference}
  def arm(armed, timers) do
    Enum.reduce(timers, armed, fn {name, ms_or_cancel}, armed ->
      if ref = armed[name], do: :erlang.cancel_timer(ref)

      case ms_or_cancel do
        :cancel -> Map.delete(armed, name)
        ms -> Map.put(armed, name, :erlang.start_timer(ms, self(), {:ddcmp, name}))
      end
    end)
  end

  @doc false
  @spec telemetry(meta, atom, map, map) :: :ok
  def telemetry(meta, event, measurements, metadata) do
    if event == :state_change do
      Logger.debug("DDCMP link #{inspect(meta.link)}: #{metadata.from} -> #{metadata.to}")
    end

    Vws.Telemetry.execute([:vws, :ddcmp, event], measurements, Map.merge(metadata, meta))
  end

  # The transport reports a failed write as a close of its own; until then nothing changes.
  defp write(nil, _frames), do: :ok
  defp write(_conn, []), do: :ok
  defp write(conn, frames), do: Transport.send(conn, Enum.map(frames, &Frame.encode/1))
end
