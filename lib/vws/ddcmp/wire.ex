defmodule Vws.DDCMP.Wire do
  @moduledoc false
  # What a process that owns a DDCMP line (`Vws.DDCMP.Link`, `Vws.VAL.Connection`,
  # `Vws.Sim.VAL2`) does with the result of a `Vws.DDCMP.Protocol` call: the I/O the pure core
  # leaves out. Frames are encoded and written to the transport as one chunk, telemetry points are
  # emitted with the line's `link`/`workstation` metadata, timers become gen_statem generic
  # timeouts named after them, and the protocol's news (`:up`, `{:data, _}`, `{:down, _}`,
  # `:peer_restarted`) is handed back, in order, for the owner to act on in the same callback.

  require Logger

  alias Vws.DDCMP.Frame
  alias Vws.Transport

  @type meta :: %{link: term, workstation: term}

  @doc false
  @spec perform([Frame.t()], [Vws.DDCMP.Protocol.event()], Transport.Conn.t() | nil, meta) ::
          {[term], [:gen_statem.action()]}
  def perform(frames, events, conn, meta) do
    write(conn, frames)

    {news, actions} =
      Enum.reduce(events, {[], []}, fn
        {:telemetry, event, measurements, metadata}, acc ->
          telemetry(meta, event, measurements, metadata)
          acc

        {:timer, name, :cancel}, {news, actions} ->
          {news, [{{:timeout, name}, :cancel} | actions]}

        {:timer, name, ms}, {news, actions} ->
          {news, [{{:timeout, name}, ms, name} | actions]}

        other, {news, actions} ->
          {[other | news], actions}
      end)

    {Enum.reverse(news), Enum.reverse(actions)}
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
