defmodule Vws.Ops.Web.JSON do
  @moduledoc """
  A small JSON encoder for the dashboard's `/api/state` (no hex packages here, and OTP 25 has no
  `:json`). Pure: no processes, no I/O.

  | Elixir                                  | JSON                           |
  |-----------------------------------------|--------------------------------|
  | `nil`, `true`, `false`                  | `null`, `true`, `false`        |
  | other atoms                             | strings                        |
  | integers, finite floats                 | numbers                        |
  | binaries                                | strings (see below)            |
  | lists                                   | arrays                         |
  | maps with atom, string or integer keys  | objects (keys sorted)          |

  Strings are escaped as RFC 8259 asks (`"`, `\\`, and every control character), and also
  U+2028/U+2029 so the text is safe inside a `<script>`. A binary that is not valid UTF-8 (bytes
  from a device link) is not an error: each invalid byte is written as the character with that
  code (Latin-1), so the output is always valid JSON. Anything else (tuples, pids, …) raises
  `ArgumentError`: convert it to a string first.

      iex> Vws.Ops.Web.JSON.encode_to_string(%{partition: :robot, status: "ERROR NO LINK TO VAL II", n: 7})
      ~s({"n":7,"partition":"robot","status":"ERROR NO LINK TO VAL II"})
      iex> Vws.Ops.Web.JSON.encode_to_string(["tab\\t", nil, 1.5, true])
      ~s(["tab\\\\t",null,1.5,true])
  """

  @type json ::
          nil
          | boolean
          | atom
          | number
          | String.t()
          | [json]
          | %{optional(atom | String.t() | integer) => json}

  @doc "Encodes a term as JSON iodata. Raises `ArgumentError` for a term JSON cannot hold."
  @spec encode(json) :: iodata
  def encode(nil), do: "null"
  def encode(true), do: "true"
  def encode(false), do: "false"
  def encode(atom) when is_atom(atom), do: string(Atom.to_string(atom))
  def encode(int) when is_integer(int), do: Integer.to_string(int)
  def encode(float) when is_float(float), do: :erlang.float_to_binary(float, [:short])
  def encode(bin) when is_binary(bin), do: string(bin)
  def encode(list) when is_list(list), do: array(list)

  def encode(map) when is_map(map) and not is_struct(map) do
    pairs =
      map
      |> Enum.map(fn {k, v} -> {key(k), v} end)
      |> Enum.sort_by(&elem(&1, 0))
      |> Enum.map(fn {k, v} -> [string(k), ?:, encode(v)] end)

    [?{, Enum.intersperse(pairs, ?,), ?}]
  end

  def encode(other), do: raise(ArgumentError, "cannot encode #{inspect(other)} as JSON")

  @doc "Encodes a term as a JSON binary."
  @spec encode_to_string(json) :: String.t()
  def encode_to_string(term), do: term |> encode() |> IO.iodata_to_binary()

  defp array(list), do: [?[, Enum.intersperse(Enum.map(list, &encode/1), ?,), ?]]

  defp key(k) when is_binary(k), do: k
  defp key(k) when is_atom(k) and k not in [nil, true, false], do: Atom.to_string(k)
  defp key(k) when is_integer(k), do: Integer.to_string(k)
  defp key(k), do: raise(ArgumentError, "cannot encode #{inspect(k)} as a JSON object key")

  defp string(bin), do: [?", escape(bin, []), ?"]

  defp escape(<<>>, acc), do: Enum.reverse(acc)
  defp escape(<<?", rest::binary>>, acc), do: escape(rest, [~S(\") | acc])
  defp escape(<<?\\, rest::binary>>, acc), do: escape(rest, [~S(\\) | acc])
  defp escape(<<?\n, rest::binary>>, acc), do: escape(rest, [~S(\n) | acc])
  defp escape(<<?\r, rest::binary>>, acc), do: escape(rest, [~S(\r) | acc])
  defp escape(<<?\t, rest::binary>>, acc), do: escape(rest, [~S(\t) | acc])
  defp escape(<<?\b, rest::binary>>, acc), do: escape(rest, [~S(\b) | acc])
  defp escape(<<?\f, rest::binary>>, acc), do: escape(rest, [~S(\f) | acc])
  defp escape(<<c, rest::binary>>, acc) when c < 0x20, do: escape(rest, [u(c) | acc])
  defp escape(<<0x2028::utf8, rest::binary>>, acc), do: escape(rest, [~S(\u2028) | acc])
  defp escape(<<0x2029::utf8, rest::binary>>, acc), do: escape(rest, [~S(\u2029) | acc])
  defp escape(<<c::utf8, rest::binary>>, acc), do: escape(rest, [<<c::utf8>> | acc])
  # not UTF-8: the byte as the Latin-1 character of that code
  defp escape(<<c, rest::binary>>, acc), do: escape(rest, [u(c) | acc])

  defp u(c), do: "\\u" <> String.pad_leading(String.downcase(Integer.to_string(c, 16)), 4, "0")
end
