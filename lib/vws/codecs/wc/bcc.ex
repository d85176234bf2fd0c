defmodule Vws.Codecs.WC.BCC do
  @moduledoc """
  The block check of the WC link (PROTOCOLS.md §1): the 8-bit sum, mod 256, of the bytes it
  covers (mode `:sum`, the default), or their XOR (mode `:xor`), sent as three ASCII decimal
  digits `000`–`255`.

      iex> Vws.Codecs.WC.BCC.compute("05A0054")
      111
      iex> Vws.Codecs.WC.BCC.encode(111)
      "111"
      iex> Vws.Codecs.WC.BCC.compute("05A0054", :xor)
      69
      iex> Vws.Codecs.WC.BCC.valid?("05A0054", "111", :sum)
      true
  """

  import Bitwise

  @type mode :: :sum | :xor
  @type t :: 0..255

  @doc "The block check of `data` in `mode` (`:sum` or `:xor`)."
  @spec compute(iodata, mode) :: t
  def compute(data, mode \\ :sum)
  def compute(data, :sum) when is_binary(data), do: sum(data, 0)
  def compute(data, :xor) when is_binary(data), do: xor(data, 0)
  def compute(data, mode) when mode in [:sum, :xor], do: compute(IO.iodata_to_binary(data), mode)

  # eight (then four) bytes a step, a step costing what a byte would; the sum is taken mod 256
  # at the end
  defp sum(<<a, b, c, d, e, f, g, h, rest::binary>>, acc),
    do: sum(rest, acc + a + b + c + d + e + f + g + h)

  defp sum(<<a, b, c, d, rest::binary>>, acc), do: sum(rest, acc + a + b + c + d)
  defp sum(<<byte, rest::binary>>, acc), do: sum(rest, acc + byte)
  defp sum(<<>>, acc), do: band(acc, 0xFF)

  defp xor(<<a, b, c, d, e, f, g, h, rest::binary>>, acc),
    do:
      xor(
        rest,
        acc
        |> bxor(a)
        |> bxor(b)
        |> bxor(c)
        |> bxor(d)
        |> bxor(e)
        |> bxor(f)
        |> bxor(g)
        |> bxor(h)
      )

  defp xor(<<a, b, c, d, rest::binary>>, acc),
    do: xor(rest, acc |> bxor(a) |> bxor(b) |> bxor(c) |> bxor(d))

  defp xor(<<byte, rest::binary>>, acc), do: xor(rest, bxor(acc, byte))
  defp xor(<<>>, acc), do: acc

  @doc "The three ASCII digits that carry `bcc` on the wire."
  @spec encode(t) :: <<_::24>>
  def encode(bcc) when is_integer(bcc) and bcc in 0..255 do
    <<?0 + div(bcc, 100), ?0 + rem(div(bcc, 10), 10), ?0 + rem(bcc, 10)>>
  end

  @doc """
  Reads a BCC field: exactly three ASCII digits with a value 0–255, else `:error`.

      iex> Vws.Codecs.WC.BCC.decode("037")
      {:ok, 37}
      iex> Vws.Codecs.WC.BCC.decode("256")
      :error
  """
  @spec decode(binary) :: {:ok, t} | :error
  def decode(<<a, b, c>>) when a in ?0..?9 and b in ?0..?9 and c in ?0..?9 do
    case (a - ?0) * 100 + (b - ?0) * 10 + (c - ?0) do
      bcc when bcc <= 255 -> {:ok, bcc}
      _ -> :error
    end
  end

  def decode(_field), do: :error

  @doc "Whether the BCC field `field` (three digits) is the block check of `data`."
  @spec valid?(iodata, binary, mode) :: boolean
  def valid?(data, field, mode \\ :sum) do
    case decode(field) do
      {:ok, bcc} -> compute(data, mode) == bcc
      :error -> false
    end
  end

  @doc false
  # The `:bcc` option shared by the WC codecs.
  @spec mode(keyword) :: mode
  def mode(opts) do
    case Keyword.get(opts, :bcc, :sum) do
      mode when mode in [:sum, :xor] -> mode
      other -> raise ArgumentError, "bcc: must be :sum or :xor, got #{inspect(other)}"
    end
  end
end
