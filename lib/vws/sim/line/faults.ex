defmodule Vws.Sim.Line.Faults do
  @moduledoc """
  The byte faults of one direction of a simulated line, as a pure value: bit errors, lost bytes
  and a cut after a number of bytes. `Vws.Sim.Line` runs one per direction of each connection;
  tests can run it alone.

  `apply/2` takes the bytes that enter the line and returns the bytes that come out of it:

    * **bit errors** — each data bit is inverted with probability `:ber` (bit error rate),
      independently of every other bit. Only the 8 data bits of a byte are modelled; a hit start,
      stop or parity bit would be a framing or parity error, which a real UART turns into a lost
      or garbled byte, and `:drop` stands for those;
    * **lost bytes** — each byte is lost with probability `:drop`;
    * **a cut** — with `disconnect_after: n`, the line is cut after the `n`-th byte that enters it
      (counted from `new/1`, or from the `configure/2` that set it): that byte and those before it
      go through, nothing after them does, and `cut?/1` turns true.

  ## Deterministic

  The draws come from `:rand` states seeded from `:seed` (any term; default 0), one stream for bit
  errors and one for lost bytes. The faults are drawn as distances to the next event (a geometric
  variate), counted in bits and in bytes of the stream. So the output depends only on the seed
  and on the byte sequence — not on how the bytes are cut into chunks — and a rate of 1e-6 costs
  nothing on the bytes in between.

      iex> faults = Vws.Sim.Line.Faults.new(ber: 1.0)
      iex> {out, faults} = Vws.Sim.Line.Faults.apply("A\\r\\n", faults)
      iex> out
      <<0xBE, 0xF2, 0xF5>>
      iex> Vws.Sim.Line.Faults.counters(faults)
      %{bytes_in: 3, bytes_out: 3, bits_flipped: 24, bytes_dropped: 0}
      iex> faults = Vws.Sim.Line.Faults.new(disconnect_after: 4)
      iex> {"*005", faults} = Vws.Sim.Line.Faults.apply("*0054*", faults)
      iex> Vws.Sim.Line.Faults.cut?(faults)
      true
  """

  import Bitwise
  import Kernel, except: [apply: 2]

  @data_bits 8
  @keys [:ber, :drop, :disconnect_after]

  @enforce_keys [:flip_rand, :drop_rand]
  defstruct ber: 0.0,
            drop: 0.0,
            disconnect_after: nil,
            flip_rand: nil,
            drop_rand: nil,
            flip_in: :infinity,
            drop_in: :infinity,
            cut_in: :infinity,
            cut?: false,
            bytes_in: 0,
            bytes_out: 0,
            bits_flipped: 0,
            bytes_dropped: 0

  # flip_in: data bits that pass intact before the next inverted one; drop_in: bytes that pass
  # before the next lost one; cut_in: bytes that may still enter before the cut. :infinity when
  # the fault is off.
  @opaque t :: %__MODULE__{
            ber: float,
            drop: float,
            disconnect_after: pos_integer | nil,
            flip_rand: :rand.state(),
            drop_rand: :rand.state(),
            flip_in: non_neg_integer | :infinity,
            drop_in: non_neg_integer | :infinity,
            cut_in: pos_integer | :infinity,
            cut?: boolean,
            bytes_in: non_neg_integer,
            bytes_out: non_neg_integer,
            bits_flipped: non_neg_integer,
            bytes_dropped: non_neg_integer
          }

  @typedoc "What a direction has done so far."
  @type counters :: %{
          bytes_in: non_neg_integer,
          bytes_out: non_neg_integer,
          bits_flipped: non_neg_integer,
          bytes_dropped: non_neg_integer
        }

  @doc """
  A fault state. Options: `:seed` (any term, default 0), `:ber` and `:drop` (probabilities from
  0.0 to 1.0, default 0.0), `:disconnect_after` (a positive number of bytes, or nil). Other
  options are ignored, so one keyword list can configure a whole line. Raises `ArgumentError`
  on a value out of range.
  """
  @spec new(keyword) :: t
  def new(opts \\ []) do
    seed = :erlang.phash2(Keyword.get(opts, :seed, 0), 1 <<< 32)

    %__MODULE__{
      flip_rand: :rand.seed_s(:exsss, {seed, 0x0B17, 1}),
      drop_rand: :rand.seed_s(:exsss, {seed, 0x0D0B, 2})
    }
    |> configure(opts)
  end

  @doc """
  Changes the faults named in `opts` (`:ber`, `:drop`, `:disconnect_after`), keeping the others
  and the random streams. A new `:disconnect_after` counts from now; nil removes the cut (one
  that has happened stays).
  """
  @spec configure(t, keyword) :: t
  def configure(%__MODULE__{} = faults, opts) do
    opts
    |> Keyword.take(@keys)
    |> Enum.reduce(faults, fn
      {:ber, p}, f ->
        p = probability!(:ber, p)
        {gap, rand} = gap(p, f.flip_rand)
        %{f | ber: p, flip_in: gap, flip_rand: rand}

      {:drop, p}, f ->
        p = probability!(:drop, p)
        {gap, rand} = gap(p, f.drop_rand)
        %{f | drop: p, drop_in: gap, drop_rand: rand}

      {:disconnect_after, nil}, f ->
        %{f | disconnect_after: nil, cut_in: :infinity}

      {:disconnect_after, n}, f when is_integer(n) and n > 0 ->
        %{f | disconnect_after: n, cut_in: n}

      {:disconnect_after, other}, _f ->
        raise ArgumentError,
              "disconnect_after must be a positive integer or nil, got #{inspect(other)}"
    end)
  end

  @doc "The faults in force, as a keyword list `configure/2` accepts."
  @spec settings(t) :: keyword
  def settings(%__MODULE__{} = f),
    do: [ber: f.ber, drop: f.drop, disconnect_after: f.disconnect_after]

  @doc """
  Passes `bytes` through the line: returns what comes out, and the state for the next bytes.
  After the cut nothing comes out and nothing is counted.
  """
  @spec apply(binary, t) :: {binary, t}
  def apply(bytes, %__MODULE__{cut?: true} = faults) when is_binary(bytes), do: {<<>>, faults}

  def apply(bytes, %__MODULE__{} = faults) when is_binary(bytes) do
    size = byte_size(bytes)
    {taken, cut?} = if faults.cut_in <= size, do: {faults.cut_in, true}, else: {size, false}
    chunk = binary_part(bytes, 0, taken)

    {flips, faults} = flips(faults, taken * @data_bits)
    {drops, faults} = drops(faults, taken)
    {out, flipped} = build(chunk, flips, drops)
    out = IO.iodata_to_binary(out)

    faults = %{
      faults
      | cut_in: if(cut?, do: 0, else: sub(faults.cut_in, taken)),
        cut?: cut?,
        bytes_in: faults.bytes_in + taken,
        bytes_out: faults.bytes_out + byte_size(out),
        bits_flipped: faults.bits_flipped + flipped,
        bytes_dropped: faults.bytes_dropped + length(drops)
    }

    {out, faults}
  end

  @doc "True once the line has been cut by `:disconnect_after`."
  @spec cut?(t) :: boolean
  def cut?(%__MODULE__{cut?: cut?}), do: cut?

  @doc """
  Bytes that entered and came out, data bits inverted in the bytes that came out, bytes lost.
  """
  @spec counters(t) :: counters
  def counters(%__MODULE__{} = f) do
    %{
      bytes_in: f.bytes_in,
      bytes_out: f.bytes_out,
      bits_flipped: f.bits_flipped,
      bytes_dropped: f.bytes_dropped
    }
  end

  @doc """
  How many trials pass before the next success, each succeeding with probability `p`:
  `:infinity` for 0, 0 for 1, else a geometric variate drawn from `rand`.
  """
  @spec gap(float, :rand.state()) :: {non_neg_integer | :infinity, :rand.state()}
  def gap(p, rand) when p <= 0, do: {:infinity, rand}
  def gap(p, rand) when p >= 1, do: {0, rand}

  def gap(p, rand) do
    # u is in (0, 1): log(u) is finite and negative.
    {u, rand} = :rand.uniform_real_s(rand)
    {trunc(:math.log(u) / log_1m(p)), rand}
  end

  # log(1 - p) without losing small p to rounding.
  defp log_1m(p) when p < 1.0e-4, do: -p - p * p / 2 - p * p * p / 3
  defp log_1m(p), do: :math.log(1 - p)

  ## Internals

  # The offsets of the inverted bits among the next `bits` data bits, ascending.
  defp flips(%{flip_in: :infinity} = f, _bits), do: {[], f}

  defp flips(f, bits) do
    {offsets, next, rand} = events(f.flip_in, bits, f.ber, f.flip_rand, 0, [])
    {offsets, %{f | flip_in: next, flip_rand: rand}}
  end

  defp drops(%{drop_in: :infinity} = f, _bytes), do: {[], f}

  defp drops(f, bytes) do
    {offsets, next, rand} = events(f.drop_in, bytes, f.drop, f.drop_rand, 0, [])
    {offsets, %{f | drop_in: next, drop_rand: rand}}
  end

  # Walks the events of a stream over `total` trials from `offset`; `until` trials pass before
  # the next event. Returns the event offsets and the distance left past the end.
  defp events(until, total, p, rand, offset, acc) do
    at = offset + until

    if at < total do
      {gap, rand} = gap(p, rand)
      events(gap, total, p, rand, at + 1, [at | acc])
    else
      {Enum.reverse(acc), at - total, rand}
    end
  end

  # The chunk with its bits inverted and its bytes dropped; counts the inverted bits that are
  # delivered.
  defp build(chunk, [], []), do: {chunk, 0}

  defp build(chunk, flips, drops) do
    masks =
      Enum.reduce(flips, %{}, fn bit, masks ->
        mask = 1 <<< rem(bit, @data_bits)
        Map.update(masks, div(bit, @data_bits), mask, &(&1 ||| mask))
      end)

    dropped = MapSet.new(drops)
    positions = masks |> Map.keys() |> Enum.concat(drops) |> Enum.uniq() |> Enum.sort()

    {parts, last, flipped} =
      Enum.reduce(positions, {[], 0, 0}, fn pos, {parts, last, flipped} ->
        parts = [binary_part(chunk, last, pos - last) | parts]

        if MapSet.member?(dropped, pos) do
          {parts, pos + 1, flipped}
        else
          mask = Map.fetch!(masks, pos)
          byte = bxor(:binary.at(chunk, pos), mask)
          {[byte | parts], pos + 1, flipped + ones(mask)}
        end
      end)

    tail = binary_part(chunk, last, byte_size(chunk) - last)
    {Enum.reverse([tail | parts]), flipped}
  end

  defp ones(0), do: 0
  defp ones(n), do: (n &&& 1) + ones(n >>> 1)

  defp sub(:infinity, _), do: :infinity
  defp sub(n, m), do: n - m

  defp probability!(_key, p) when is_number(p) and p >= 0 and p <= 1, do: p / 1

  defp probability!(key, p),
    do: raise(ArgumentError, "#{key} must be a probability from 0.0 to 1.0, got #{inspect(p)}")
end
