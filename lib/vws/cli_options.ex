defmodule Vws.CLIOptions do
  @moduledoc """
  The command-line flags of every VWS command (`mix vws.serve`, `mix vws.demo`, `mix vws.wc`,
  `mix vws.hydraulic`, `mix vws.library`, `mix vws.drip_feed` and the release's `bin/vws-*`),
  parsed and checked in one place, so that a wrong flag is answered the same way everywhere: one
  line naming the flag and what is wrong with it — never an Elixir term.

      iex> Vws.CLIOptions.parse(["--wc-port", "abc"], wc_port: :port)
      {:error, "--wc-port: abc is not a port number (1-65535)"}
      iex> Vws.CLIOptions.parse(["--wc-port", "7071", "x"], wc_port: :port)
      {:ok, [wc_port: 7071], ["x"]}
      iex> Vws.CLIOptions.parse(["--wc-prot", "7071"], wc_port: :port, bind: :string)
      {:error, "--wc-prot: unknown option (did you mean --wc-port?)"}
      iex> Vws.CLIOptions.parse(["--time-scale", "0"], time_scale: :positive_float)
      {:error, "--time-scale: 0 is not a number above 0"}
      iex> Vws.CLIOptions.parse(["--id"], id: :string)
      {:error, "--id: needs a value"}

  Types: OptionParser's `:string`, `:boolean`, `:integer`, `:float`, `:count`, and

    * `:port` — a TCP port, 1-65535
    * `:port_or_zero` — 0-65535, 0 picking a free port
    * `:pos_integer`, `:non_neg_integer`
    * `:positive_float` — a number above 0 (integers accepted: `--time-scale 20`)
    * `:probability` — a number from 0 to 1 (`--ber 1e-4`)
    * `{:in, ["sum", "xor"]}` — one of the given words
  """

  @type type ::
          :string
          | :boolean
          | :integer
          | :float
          | :count
          | :port
          | :port_or_zero
          | :pos_integer
          | :non_neg_integer
          | :positive_float
          | :probability
          | {:in, [String.t()]}

  @doc """
  Parses `argv` against `switches` (`name: type`): `{:ok, opts, rest}` or `{:error, line}` for the
  first flag that is unknown, lacks its value or has a wrong one.
  """
  @spec parse([String.t()], keyword(type)) :: {:ok, keyword, [String.t()]} | {:error, String.t()}
  def parse(argv, switches) do
    # every value is read as a string here and checked below, with words for what is wrong
    strict = Enum.map(switches, fn {k, t} -> {k, base(t)} end)
    {opts, rest, invalid} = OptionParser.parse(argv, strict: strict)

    with :ok <- invalid(invalid, switches),
         {:ok, opts} <- check(opts, switches) do
      {:ok, opts, rest}
    end
  end

  @doc """
  For a mix task: the options of `argv`, or `Mix.raise/1` with the line (`** (Mix) --wc-port: abc
  is not a port number (1-65535)`, exit status 1). Arguments that are not options are refused
  too, unless `args: true` — then `{opts, args}` is returned.
  """
  @spec parse!([String.t()], keyword(type), keyword) :: keyword | {keyword, [String.t()]}
  def parse!(argv, switches, options \\ []) do
    case parse(argv, switches) do
      {:ok, opts, rest} ->
        cond do
          Keyword.get(options, :args, false) -> {opts, rest}
          rest == [] -> opts
          true -> Mix.raise("#{hd(rest)}: unexpected argument (every option starts with --)")
        end

      {:error, line} ->
        Mix.raise(line)
    end
  end

  @doc "The flag of option `name`: `:wc_port` → `\"--wc-port\"`."
  @spec flag(atom) :: String.t()
  def flag(name), do: "--" <> String.replace(Atom.to_string(name), "_", "-")

  defp base(t) when t in [:boolean, :count], do: t
  defp base(_t), do: :string

  defp invalid([], _switches), do: :ok

  defp invalid([{flag, value} | _], switches) do
    known = Enum.map(switches, fn {k, _} -> flag(k) end)
    # OptionParser gives `--no-x` for a boolean's negation and `--x` for others
    name = flag |> String.split("=", parts: 2) |> hd()

    cond do
      name in known and value == nil ->
        {:error, "#{name}: needs a value"}

      name in known ->
        {:error, "#{name}: #{value} is not accepted"}

      true ->
        case Enum.max_by(known, &String.jaro_distance(&1, name), fn -> nil end) do
          nil ->
            {:error, "#{name}: unknown option (this command takes none)"}

          near ->
            if String.jaro_distance(near, name) >= 0.85,
              do: {:error, "#{name}: unknown option (did you mean #{near}?)"},
              else: {:error, "#{name}: unknown option (known: #{Enum.join(known, " ")})"}
        end
    end
  end

  defp check(opts, switches) do
    Enum.reduce_while(opts, {:ok, []}, fn {key, value}, {:ok, acc} ->
      case convert(Keyword.fetch!(switches, key), value) do
        {:ok, v} -> {:cont, {:ok, [{key, v} | acc]}}
        {:error, what} -> {:halt, {:error, "#{flag(key)}: #{value} #{what}"}}
      end
    end)
    |> case do
      {:ok, acc} -> {:ok, Enum.reverse(acc)}
      error -> error
    end
  end

  defp convert(t, v) when t in [:boolean, :count], do: {:ok, v}
  defp convert(:string, v), do: {:ok, v}

  defp convert({:in, words}, v) do
    if v in words,
      do: {:ok, v},
      else: {:error, "is not one of #{Enum.join(words, ", ")}"}
  end

  defp convert(:port, v), do: integer(v, 1..65_535, "is not a port number (1-65535)")

  defp convert(:port_or_zero, v),
    do: integer(v, 0..65_535, "is not a port number (0-65535; 0 picks a free one)")

  defp convert(:pos_integer, v), do: integer(v, 1..0x7FFFFFFF, "is not a whole number above 0")
  defp convert(:non_neg_integer, v), do: integer(v, 0..0x7FFFFFFF, "is not a whole number")
  defp convert(:integer, v), do: integer(v, -0x7FFFFFFF..0x7FFFFFFF, "is not a whole number")
  defp convert(:float, v), do: number(v, fn _ -> true end, "is not a number")
  defp convert(:positive_float, v), do: number(v, &(&1 > 0), "is not a number above 0")

  defp convert(:probability, v),
    do: number(v, &(&1 >= 0 and &1 <= 1), "is not a number from 0 to 1")

  defp integer(v, range, what) do
    case Integer.parse(v) do
      {n, ""} -> if n in range, do: {:ok, n}, else: {:error, what}
      _ -> {:error, what}
    end
  end

  defp number(v, ok?, what) do
    case Float.parse(v) do
      {x, ""} -> if ok?.(x), do: {:ok, x}, else: {:error, what}
      _ -> {:error, what}
    end
  end
end
