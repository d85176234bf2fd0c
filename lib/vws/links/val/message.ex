defmodule Vws.Links.VAL.Message do
  @moduledoc """
  The VAL data message (seed §4.3.4, Fig. 10; PROTOCOLS.md §3): the record carried in the data
  field of one DDCMP data message. Pure: no processes, no I/O.

      byte 0   LUN          logical unit: 0 network manager, 1 short status, 2 monitor I/O,
                            3 monitor asynchronous output, 4 program terminal, 5 disk
      byte 1   function     1 WRITE (text for the peer), 2 READ (the LUN asks for input),
                            3 REPLY (the answer to a LUN-initiated message)
      byte 2   qualifier    more control information; on LUN 3 the message code:
                            1 MOTION BEGIN, 2 MOTION COMPLETE, 3 PROGRAM START,
                            4 PROGRAM COMPLETE, 5 ERROR
      byte 3…  text         0–256 bytes of 7-bit ASCII

  DDCMP frames the message and checks it (CRC-16), so this codec needs no length or check
  of its own and decodes one whole message at a time. On LUN 3 the qualifier decodes to the
  message-code name (`:motion_begin` …); an unknown code stays a number.

      iex> Vws.Links.VAL.Message.encode(%Vws.Links.VAL.Message{lun: 2, function: :write, text: "DO MOVE SAFE"})
      ...> |> IO.iodata_to_binary()
      <<2, 1, 0, "DO MOVE SAFE">>
      iex> Vws.Links.VAL.Message.decode(<<3, 1, 2, "MOTION COMPLETE">>)
      {:ok, %Vws.Links.VAL.Message{lun: 3, function: :write, qualifier: :motion_complete, text: "MOTION COMPLETE"}}
      iex> {:error, %Vws.Links.VAL.Error{reason: reason}} = Vws.Links.VAL.Message.decode(<<2, 9, 0>>)
      iex> reason
      :bad_function
  """

  alias Vws.Links.VAL.Error

  @lun_network_manager 0
  @lun_short_status 1
  @lun_monitor 2
  @lun_async 3
  @max_lun 5

  @write 1
  @read 2
  @reply 3

  @max_text 256

  @functions %{write: @write, read: @read, reply: @reply}
  @function_names Map.new(@functions, fn {name, code} -> {code, name} end)

  @message_codes %{
    motion_begin: 1,
    motion_complete: 2,
    program_start: 3,
    program_complete: 4,
    error: 5
  }
  @message_code_names Map.new(@message_codes, fn {name, code} -> {code, name} end)

  defstruct lun: @lun_monitor, function: :write, qualifier: 0, text: ""

  @type function_code :: :write | :read | :reply
  @type message_code ::
          :motion_begin | :motion_complete | :program_start | :program_complete | :error
  @type t :: %__MODULE__{
          lun: 0..5,
          function: function_code,
          qualifier: 0..255 | message_code,
          text: binary
        }

  @doc "The LUN numbers by name: network manager 0, short status 1, monitor 2, asynchronous 3."
  @spec lun(:network_manager | :short_status | :monitor | :async) :: 0..3
  def lun(:network_manager), do: @lun_network_manager
  def lun(:short_status), do: @lun_short_status
  def lun(:monitor), do: @lun_monitor
  def lun(:async), do: @lun_async

  @doc "The LUN 3 message codes by name."
  @spec message_codes() :: %{message_code => 1..5}
  def message_codes, do: @message_codes

  @doc "The largest message text, in bytes."
  @spec max_text() :: 256
  def max_text, do: @max_text

  @doc """
  Builds a message, checking every field; errors are values.

      iex> Vws.Links.VAL.Message.new(3, :write, :motion_begin, "MOTION BEGIN")
      {:ok, %Vws.Links.VAL.Message{lun: 3, function: :write, qualifier: :motion_begin, text: "MOTION BEGIN"}}
      iex> {:error, e} = Vws.Links.VAL.Message.new(2, :write, 0, String.duplicate("X", 257))
      iex> e.reason
      :too_long
  """
  @spec new(0..5, function_code, 0..255 | message_code, binary) :: {:ok, t} | {:error, Error.t()}
  def new(lun, function, qualifier \\ 0, text \\ "") do
    with :ok <- check_lun(lun),
         :ok <- check_function(function),
         {:ok, qualifier} <- check_qualifier(lun, qualifier),
         :ok <- check_text(text) do
      {:ok, %__MODULE__{lun: lun, function: function, qualifier: qualifier, text: text}}
    end
  end

  @doc """
  The bytes of a message (iodata). Raises `ArgumentError` for a message `new/4` would refuse:
  callers with text from outside build it with `new/4` first.
  """
  @spec encode(t) :: iodata
  def encode(%__MODULE__{lun: lun, function: function, qualifier: qualifier, text: text} = m) do
    case new(lun, function, qualifier, text) do
      {:ok, _} ->
        [lun, Map.fetch!(@functions, function), qualifier_byte(qualifier), text]

      {:error, error} ->
        raise ArgumentError,
              "cannot encode VAL message #{inspect(m, limit: 8)}: #{Exception.message(error)}"
    end
  end

  @doc "Decodes the data field of one DDCMP data message."
  @spec decode(binary) :: {:ok, t} | {:error, Error.t()}
  def decode(<<lun, function, qualifier, text::binary>>) do
    cond do
      lun > @max_lun ->
        {:error, %Error{reason: :bad_lun, value: lun}}

      not is_map_key(@function_names, function) ->
        {:error, %Error{reason: :bad_function, value: function}}

      true ->
        with :ok <- check_text(text) do
          {:ok,
           %__MODULE__{
             lun: lun,
             function: Map.fetch!(@function_names, function),
             qualifier: qualifier_name(lun, qualifier),
             text: text
           }}
        end
    end
  end

  def decode(bin) when is_binary(bin), do: {:error, %Error{reason: :too_short}}

  defp check_lun(lun) when is_integer(lun) and lun in 0..@max_lun, do: :ok
  defp check_lun(lun), do: {:error, %Error{reason: :bad_lun, value: lun}}

  defp check_function(f) when is_map_key(@functions, f), do: :ok
  defp check_function(f), do: {:error, %Error{reason: :bad_function, value: f}}

  defp check_qualifier(lun, q) when is_integer(q) and q in 0..255,
    do: {:ok, qualifier_name(lun, q)}

  defp check_qualifier(@lun_async, q) when is_map_key(@message_codes, q), do: {:ok, q}
  defp check_qualifier(_lun, q), do: {:error, %Error{reason: :bad_qualifier, value: q}}

  defp check_text(text) when is_binary(text) and byte_size(text) > @max_text,
    do: {:error, %Error{reason: :too_long, value: byte_size(text)}}

  defp check_text(text) when is_binary(text) do
    case first_non_ascii(text, 0) do
      nil -> :ok
      at -> {:error, %Error{reason: :not_ascii, value: at}}
    end
  end

  defp check_text(other), do: {:error, %Error{reason: :not_ascii, value: other}}

  defp first_non_ascii(<<>>, _at), do: nil
  defp first_non_ascii(<<b, rest::binary>>, at) when b < 0x80, do: first_non_ascii(rest, at + 1)
  defp first_non_ascii(_, at), do: at

  defp qualifier_name(@lun_async, q) when is_map_key(@message_code_names, q),
    do: Map.fetch!(@message_code_names, q)

  defp qualifier_name(_lun, q), do: q

  defp qualifier_byte(q) when is_atom(q), do: Map.fetch!(@message_codes, q)
  defp qualifier_byte(q), do: q
end
