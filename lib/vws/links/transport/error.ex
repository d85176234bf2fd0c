defmodule Vws.Links.Transport.Error do
  @moduledoc """
  Why a transport could not do what it was asked: every `{:error, _}` of `Vws.Links.Transport`
  (`connect/2`, `listen/2`, `accept/2`, `send/2`, `controlling_process/2`, `handle_message/2`) is
  `{:error, %Vws.Links.Transport.Error{reason: reason}}`, whatever the transport. An endpoint string
  that cannot be read is a different thing, a `Vws.Links.Endpoint.Error`, and is returned as it is.

  Reasons:

    * `:closed` — the connection (or the listener) is closed;
    * `:timeout` — nothing came within the time given (`accept/2`, a TCP dial);
    * `:econnrefused` — nothing listens at the endpoint;
    * `:eaddrinuse` — something listens there already;
    * `:not_owner` — only the connection's controlling process may hand it on;
    * `:not_listenable` — a tty or a `cell:` endpoint is connected to, never listened on;
    * `:not_resolved` — a `cell:` endpoint given to the transports as it is: it names a
      workstation and is resolved above them (`Vws.CEC.Cell.connect/2`);
    * `:not_found`, `:not_listening`, `:not_reachable` — a `cell:` endpoint: no node of the cell
      runs the workstation, its SUN_COMM is not listening yet, its WC link is a serial line;
    * `:enoent`, `:eacces`, `:not_a_tty` — a tty path that does not exist, may not be opened,
      or is not a terminal device;
    * `:socat_not_found`, `{:socat_exit, status}` — the serial transport's `socat` is missing, or
      ended (the device could not be opened, or went away);
    * `:com_port_refused`, `{:setting_refused, key, asked, answered}`, `:negotiation_timeout` —
      an `rfc2217://` terminal server that will not do RFC 2217, would not set a setting of the
      endpoint (it answered another value), or did not finish negotiating in time;
    * `:device_gone` — the serial device went away while open (its path no longer exists: a USB
      adapter pulled out, a cable server's pty closed);
    * `{:unknown_backend, backend}` — a serial backend other than `:socat` or `:circuits_uart`;
    * any other `:inet` error (`:etimedout`, `:econnreset`, `:ehostunreach`, `:nxdomain`, …), and
      a text where the transport could say more (an address that cannot be resolved).

      iex> Exception.message(%Vws.Links.Transport.Error{reason: :econnrefused})
      "connection refused: nothing listens at that endpoint (is the device or simulator running?)"
  """

  defexception [:reason]

  @type t :: %__MODULE__{reason: term}

  @doc false
  # The facade's one place of wrapping: an implementation's `{:error, reason}` as this struct.
  @spec wrap(term) :: term
  def wrap({:error, %__MODULE__{}} = error), do: error
  def wrap({:error, %Vws.Links.Endpoint.Error{}} = error), do: error
  def wrap({:error, reason}), do: {:error, %__MODULE__{reason: reason}}
  def wrap(other), do: other

  @impl true
  def message(%__MODULE__{reason: reason}), do: words(reason)

  defp words(:closed), do: "the connection is closed"
  defp words(:timeout), do: "timed out"

  defp words(:econnrefused),
    do:
      "connection refused: nothing listens at that endpoint (is the device or simulator running?)"

  defp words(:eaddrinuse), do: "address in use: something listens at that endpoint already"
  defp words(:not_owner), do: "only the connection's controlling process may hand it on"

  defp words(:not_listenable),
    do: "this endpoint cannot be listened on (a tty or a cell: endpoint is connected to)"

  defp words(:not_resolved),
    do: "a cell: endpoint names a workstation: connect to it with Vws.CEC.Cell.connect/2"

  defp words(:not_found), do: "no node of the cell runs that workstation"
  defp words(:not_listening), do: "the workstation's SUN_COMM is not listening yet; try again"

  defp words(:not_reachable),
    do: "the workstation's WC link is a serial line: it cannot be reached through the cell"

  defp words(:enoent), do: "no such device"

  defp words(:eacces),
    do: "permission denied on the device (is the user in the dialout group?)"

  defp words(:not_a_tty), do: "the path is not a terminal device"
  defp words(:socat_not_found), do: "socat is not installed (apt-get install socat)"

  defp words({:socat_exit, status}),
    do: "socat ended with status #{status}: the device could not be opened, or went away"

  defp words(:device_gone),
    do:
      "the serial device went away (cable pulled or USB adapter removed); " <>
        "it is reopened when it is back"

  defp words(:com_port_refused),
    do:
      "the terminal server refused RFC 2217 (COM-PORT-OPTION): enable it there " <>
        "(ser2net: telnet(rfc2217)), or use tcp:// without serial settings"

  defp words({:setting_refused, key, asked, answered}),
    do:
      "the terminal server would not set #{key} to #{asked} " <>
        "(it answered #{inspect(answered)}): its port cannot do that"

  defp words(:negotiation_timeout),
    do: "the terminal server did not finish RFC 2217 negotiation in time"

  defp words({:unknown_backend, backend}),
    do: "unknown serial backend #{inspect(backend)} (known: :socat, :circuits_uart)"

  defp words(text) when is_binary(text), do: text

  defp words(reason) when is_atom(reason) do
    case :inet.format_error(reason) do
      ~c"unknown POSIX error" ++ _ -> "transport error #{inspect(reason)}"
      text -> List.to_string(text)
    end
  end

  defp words(reason), do: "transport error #{inspect(reason)}"
end
