defmodule Vws.Codecs.WC.Command do
  @moduledoc """
  One command `Mi` of a WC command string (PROTOCOLS.md §1): the command-set letter `C`, the
  four-digit command number `NNNN` within that set, and the command text.

  The sets are R robot, M Monarch, F fixture (vise), H hydraulic, G gripper, V vacuum, S status
  and A acknowledgement. Any other uppercase letter decodes as `{:unknown, letter}`: the codec
  only checks the syntax, SUN_COMM decides what an unknown set means.

  The text is printable ASCII (0x20–0x7E) without `*`, the field separator. It has at least one
  character, except for an `A` command, whose text may be empty (decision: an acknowledgement
  needs no words, every other command does).

      iex> Vws.Codecs.WC.Command.new(:gripper, 4, "OPEN")
      %Vws.Codecs.WC.Command{letter: "G", set: :gripper, number: 4, text: "OPEN"}
      iex> Vws.Codecs.WC.Command.set_for_letter("Q")
      {:unknown, "Q"}
  """

  @enforce_keys [:letter, :set, :number, :text]
  defstruct [:letter, :set, :number, :text]

  @type set ::
          :robot
          | :monarch
          | :fixture
          | :hydraulic
          | :gripper
          | :vacuum
          | :status
          | :ack
          | {:unknown, String.t()}

  @type t :: %__MODULE__{
          letter: String.t(),
          set: set,
          number: 0..9999,
          text: String.t()
        }

  @sets %{
    "R" => :robot,
    "M" => :monarch,
    "F" => :fixture,
    "H" => :hydraulic,
    "G" => :gripper,
    "V" => :vacuum,
    "S" => :status,
    "A" => :ack
  }
  @letters Map.new(@sets, fn {letter, set} -> {set, letter} end)

  @doc """
  The command set named by a single uppercase letter; a letter outside `RMFHGVSA` gives
  `{:unknown, letter}`.
  """
  @spec set_for_letter(String.t()) :: set
  def set_for_letter(<<byte>> = letter) when byte in ?A..?Z,
    do: Map.get(@sets, letter, {:unknown, letter})

  @doc "The letter of a command set; the inverse of `set_for_letter/1`."
  @spec letter_for_set(set) :: String.t()
  def letter_for_set({:unknown, <<byte>> = letter}) when byte in ?A..?Z, do: letter
  def letter_for_set(set) when is_map_key(@letters, set), do: Map.fetch!(@letters, set)

  @doc """
  A command of `set` (an atom, `{:unknown, letter}` or the letter itself). Raises `ArgumentError`
  if the number or text could not be sent.
  """
  @spec new(set | String.t(), 0..9999, String.t()) :: t
  def new(set_or_letter, number, text) do
    letter = if is_binary(set_or_letter), do: set_or_letter, else: letter_for_set(set_or_letter)

    command = %__MODULE__{letter: letter, set: set_for_letter(letter), number: number, text: text}

    case check(command) do
      :ok -> command
      {:error, why} -> raise ArgumentError, why
    end
  end

  @doc false
  # Why `command` could not be encoded, for the encoders' ArgumentError.
  @spec check(t) :: :ok | {:error, String.t()}
  def check(%__MODULE__{letter: letter, set: set, number: number, text: text} = command) do
    cond do
      not letter?(letter) ->
        {:error, "command letter must be one uppercase letter: #{inspect(command)}"}

      set_for_letter(letter) != set ->
        {:error, "command letter #{letter} does not name set #{inspect(set)}"}

      not (is_integer(number) and number in 0..9999) ->
        {:error, "command number must be 0..9999: #{inspect(command)}"}

      not (is_binary(text) and text?(text)) ->
        {:error, "command text must be printable ASCII without '*': #{inspect(command)}"}

      text == "" and letter != "A" ->
        {:error, "command text may be empty only for an A command: #{inspect(command)}"}

      true ->
        :ok
    end
  end

  @doc false
  # Parses one `Mi` field of an intact string.
  @spec parse(binary) :: {:ok, t} | :error
  def parse(<<letter, digits::binary-size(4), text::binary>>)
      when letter in ?A..?Z and (text != "" or letter == ?A) do
    with {:ok, number} <- digits(digits),
         true <- text?(text) do
      {:ok,
       %__MODULE__{
         letter: <<letter>>,
         set: set_for_letter(<<letter>>),
         number: number,
         text: text
       }}
    else
      _ -> :error
    end
  end

  def parse(_field), do: :error

  @doc false
  # The value of exactly four ASCII digits.
  @spec digits(binary) :: {:ok, 0..9999} | :error
  def digits(<<a, b, c, d>>) when a in ?0..?9 and b in ?0..?9 and c in ?0..?9 and d in ?0..?9,
    do: {:ok, (a - ?0) * 1000 + (b - ?0) * 100 + (c - ?0) * 10 + (d - ?0)}

  def digits(_field), do: :error

  @doc """
  A number as the four digits the wire carries (command, sequence and line numbers). The one
  place this is written: replies, the WC client, the dashboard and the iex views all use it.

      iex> Vws.Codecs.WC.Command.pad4(42)
      "0042"
  """
  @spec pad4(0..9999) :: binary
  def pad4(n) when is_integer(n) and n in 0..9999,
    do:
      <<?0 + div(n, 1000), ?0 + rem(div(n, 100), 10), ?0 + rem(div(n, 10), 10), ?0 + rem(n, 10)>>

  defp letter?(<<byte>>) when byte in ?A..?Z, do: true
  defp letter?(_), do: false

  defguardp text_byte(byte) when byte in 0x20..0x7E and byte != ?*

  # eight bytes a step where it can (a step costs what a byte would)
  defp text?(<<a, b, c, d, e, f, g, h, rest::binary>>)
       when text_byte(a) and text_byte(b) and text_byte(c) and text_byte(d) and text_byte(e) and
              text_byte(f) and text_byte(g) and text_byte(h),
       do: text?(rest)

  defp text?(<<byte, rest::binary>>) when text_byte(byte), do: text?(rest)
  defp text?(<<>>), do: true
  defp text?(_), do: false
end
