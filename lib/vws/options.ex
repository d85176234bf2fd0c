defmodule Vws.Options do
  @moduledoc """
  Start options checked once, in the caller, against one schema (as Redix checks its start
  options): an unknown option or a bad value is refused before any process starts, with one
  error that names the option.

      iex> schema = [port: [type: :non_neg_integer, default: 7070], bcc: [type: {:in, [:sum, :xor]}, default: :sum]]
      iex> Vws.Options.validate([bcc: :xor], schema, "SUN_COMM")
      {:ok, [port: 7070, bcc: :xor]}
      iex> {:error, error} = Vws.Options.validate([bcc: :crc], schema, "SUN_COMM")
      iex> Exception.message(error)
      "invalid SUN_COMM option :bcc: expected one of [:sum, :xor], got :crc"
      iex> {:error, error} = Vws.Options.validate([baud: 9600], schema, "SUN_COMM")
      iex> Exception.message(error)
      "unknown SUN_COMM option :baud (known: :port, :bcc)"

  A schema is a keyword list of `option: spec`; a spec has `:type`, and `:default` or
  `required: true`. Types: `:any`, `:boolean`, `:pos_integer`, `:non_neg_integer`,
  `:string`, `:keyword_list`, `:list`, `{:in, values}`, `nil` (the value `nil`),
  `{:or, types}` and `{:custom, fun}` where `fun.(value)` returns `{:ok, value}` or
  `{:error, "expected …"}`. The options come back in schema order, defaults filled in.
  """

  defmodule Error do
    @moduledoc """
    A start option that is unknown, missing or of the wrong kind: `key`, `value`, the component
    (`what`) and `message/1` saying what was expected.
    """
    defexception [:what, :key, :value, :reason, :expected]

    @type t :: %__MODULE__{
            what: String.t(),
            key: atom,
            value: term,
            reason: :unknown | :missing | :invalid | :not_a_keyword_list,
            expected: String.t() | nil
          }

    @impl true
    def message(%__MODULE__{reason: :unknown} = e),
      do: "unknown #{e.what} option #{inspect(e.key)} (known: #{e.expected})"

    def message(%__MODULE__{reason: :missing} = e),
      do: "missing #{e.what} option #{inspect(e.key)}"

    def message(%__MODULE__{reason: :not_a_keyword_list} = e),
      do: "#{e.what} options must be a keyword list, got #{inspect(e.value, limit: 10)}"

    def message(%__MODULE__{reason: :invalid} = e),
      do:
        "invalid #{e.what} option #{inspect(e.key)}: #{e.expected}, got #{inspect(e.value, limit: 10)}"
  end

  @type schema :: keyword(keyword)

  @doc "Checks `opts` against `schema`; `what` names the component in the error."
  @spec validate(term, schema, String.t()) :: {:ok, keyword} | {:error, Error.t()}
  def validate(opts, schema, what) do
    if Keyword.keyword?(opts) do
      with :ok <- unknown(opts, schema, what) do
        Enum.reduce_while(schema, {:ok, []}, fn {key, spec}, {:ok, acc} ->
          case value(opts, key, spec, what) do
            {:ok, :absent} -> {:cont, {:ok, acc}}
            {:ok, value} -> {:cont, {:ok, [{key, value} | acc]}}
            {:error, _} = error -> {:halt, error}
          end
        end)
        |> case do
          {:ok, acc} -> {:ok, Enum.reverse(acc)}
          error -> error
        end
      end
    else
      {:error, %Error{what: what, value: opts, reason: :not_a_keyword_list}}
    end
  end

  @doc "Like `validate/3`, raising `Vws.Options.Error`."
  @spec validate!(term, schema, String.t()) :: keyword
  def validate!(opts, schema, what) do
    case validate(opts, schema, what) do
      {:ok, opts} -> opts
      {:error, error} -> raise error
    end
  end

  defp unknown(opts, schema, what) do
    case Enum.find(opts, fn {key, _} -> not Keyword.has_key?(schema, key) end) do
      nil ->
        :ok

      {key, value} ->
        known = schema |> Keyword.keys() |> Enum.map_join(", ", &inspect/1)
        {:error, %Error{what: what, key: key, value: value, reason: :unknown, expected: known}}
    end
  end

  defp value(opts, key, spec, what) do
    case Keyword.fetch(opts, key) do
      {:ok, value} ->
        case check(spec[:type], value) do
          {:ok, value} ->
            {:ok, value}

          {:error, expected} ->
            {:error,
             %Error{what: what, key: key, value: value, reason: :invalid, expected: expected}}
        end

      :error ->
        cond do
          spec[:required] -> {:error, %Error{what: what, key: key, reason: :missing}}
          Keyword.has_key?(spec, :default) -> {:ok, spec[:default]}
          true -> {:ok, :absent}
        end
    end
  end

  defp check(:any, v), do: {:ok, v}
  defp check(nil, nil), do: {:ok, nil}
  defp check(nil, _), do: {:error, "expected nil"}
  defp check(:boolean, v) when is_boolean(v), do: {:ok, v}
  defp check(:boolean, _), do: {:error, "expected true or false"}
  defp check(:pos_integer, v) when is_integer(v) and v > 0, do: {:ok, v}
  defp check(:pos_integer, _), do: {:error, "expected a positive integer"}
  defp check(:non_neg_integer, v) when is_integer(v) and v >= 0, do: {:ok, v}
  defp check(:non_neg_integer, _), do: {:error, "expected a non-negative integer"}
  defp check(:string, v) when is_binary(v), do: {:ok, v}
  defp check(:string, _), do: {:error, "expected a string"}
  defp check(:list, v) when is_list(v), do: {:ok, v}
  defp check(:list, _), do: {:error, "expected a list"}

  defp check(:keyword_list, v) do
    if Keyword.keyword?(v), do: {:ok, v}, else: {:error, "expected a keyword list"}
  end

  defp check({:in, values}, v) do
    if v in values, do: {:ok, v}, else: {:error, "expected one of #{inspect(values)}"}
  end

  defp check({:custom, fun}, v), do: fun.(v)

  defp check({:or, types}, v) do
    Enum.reduce_while(types, {:error, []}, fn type, {:error, expected} ->
      case check(type, v) do
        {:ok, v} ->
          {:halt, {:ok, v}}

        {:error, why} ->
          {:cont, {:error, [String.replace_prefix(why, "expected ", "") | expected]}}
      end
    end)
    |> case do
      {:ok, v} -> {:ok, v}
      {:error, expected} -> {:error, "expected " <> Enum.join(Enum.reverse(expected), " or ")}
    end
  end
end
