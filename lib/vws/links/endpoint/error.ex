defmodule Vws.Links.Endpoint.Error do
  @moduledoc """
  Why an endpoint string was refused by `Vws.Links.Endpoint.parse/1`.

  `input` is the string as given and `detail` (possibly `nil`) the offending piece. Reasons:

    * `:not_a_string` — the endpoint was not a string at all;
    * `:unknown_scheme` — it starts with none of `tcp://`, `tty:`, `loopback:`, `cell:` or `/`;
    * `:missing_port` — a `tcp://` endpoint without `:port`;
    * `:bad_host` — the host is neither a host name nor a dotted IPv4 address (IPv6 is not supported);
    * `:bad_port` — the port is not a number from 0 to 65535;
    * `:bad_path` — the tty path is empty, relative, or holds characters a device path never has;
    * `:bad_option` — a tty setting is not written `key=value`;
    * `:unknown_option` — a serial setting other than `baud`, `data_bits`, `parity`, `stop_bits`,
      `flow`;
    * `:duplicate_option` — the same tty setting given twice;
    * `:bad_baud` — a baud rate the serial driver does not know (see `Vws.Links.Endpoint.bauds/0`);
    * `:bad_data_bits` — data bits other than 5, 6, 7 or 8;
    * `:bad_parity` — parity other than `none`, `even` or `odd`;
    * `:bad_stop_bits` — stop bits other than 1 or 2;
    * `:bad_flow` — flow control other than `none`, `xonxoff` or `rtscts`;
    * `:serial_on_tcp` — serial settings on a `tcp://` endpoint, which carries bytes only (use
      `rfc2217://` for a terminal server that can set its port);
    * `:bad_name` — the loopback name (or cell workstation id) is empty, too long, or holds spaces or
      control characters.

      iex> Exception.message(%Vws.Links.Endpoint.Error{reason: :bad_parity, input: "tty:/dev/ttyS0?parity=mark", detail: "mark"})
      ~s[invalid endpoint "tty:/dev/ttyS0?parity=mark": parity must be none, even or odd (got "mark")]
  """

  defexception [:reason, :input, :detail]

  @type reason ::
          :not_a_string
          | :unknown_scheme
          | :missing_port
          | :bad_host
          | :bad_port
          | :bad_path
          | :bad_option
          | :unknown_option
          | :duplicate_option
          | :bad_baud
          | :bad_data_bits
          | :bad_parity
          | :bad_stop_bits
          | :bad_flow
          | :serial_on_tcp
          | :bad_name

  @type t :: %__MODULE__{reason: reason(), input: term(), detail: String.t() | nil}

  @impl true
  def message(%__MODULE__{reason: reason, input: input, detail: detail}) do
    "invalid endpoint #{inspect(input, limit: 10, printable_limit: 80)}: " <>
      explain(reason) <> got(reason, detail)
  end

  defp explain(:not_a_string), do: "an endpoint must be a string"

  defp explain(:unknown_scheme),
    do:
      "expected tcp://host:port, rfc2217://host:port, tty:/dev/<device>, a /dev path, " <>
        "loopback:<name> or cell:<workstation id>"

  defp explain(:missing_port), do: "a tcp endpoint needs a port, as in tcp://host:port"
  defp explain(:bad_host), do: "the host must be a host name or an IPv4 address"
  defp explain(:bad_port), do: "the port must be a number from 0 to 65535"
  defp explain(:bad_path), do: "the tty path is not a usable device path"
  defp explain(:bad_option), do: "tty settings are written key=value and joined with &"

  defp explain(:unknown_option),
    do: "the serial settings are baud, data_bits, parity, stop_bits and flow"

  defp explain(:duplicate_option), do: "a tty setting is given twice"
  defp explain(:bad_baud), do: "the baud rate is not a standard serial speed (e.g. 9600)"
  defp explain(:bad_data_bits), do: "data_bits must be 5, 6, 7 or 8"
  defp explain(:bad_parity), do: "parity must be none, even or odd"
  defp explain(:bad_stop_bits), do: "stop_bits must be 1 or 2"
  defp explain(:bad_flow), do: "flow must be none, xonxoff or rtscts"

  defp explain(:serial_on_tcp),
    do:
      "a tcp:// endpoint carries bytes only and cannot set a serial port: " <>
        "use rfc2217://host:port?… for a terminal server that can"

  defp explain(:bad_name),
    do: "the loopback name or workstation id must be printable text without spaces"

  defp explain(other), do: inspect(other)

  # Reasons whose detail repeats a sentence are shown with it; value errors quote the value.
  defp got(_reason, nil), do: ""

  defp got(reason, detail) when reason in [:bad_host, :bad_path, :bad_name],
    do: " (#{detail})"

  defp got(_reason, detail), do: " (got #{inspect(detail)})"
end
