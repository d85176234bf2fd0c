defmodule Vws.Links.RS232.Framing do
  @moduledoc """
  How an NC program travels on a plain RS-232 line (profile `rs232-xonxoff`, docs/serial.md): a
  pure codec, no process, no I/O.

  A program is held as DNC text (`Vws.Links.DNC.Program`): lines ending in LF, the first and the
  last one `%`. On the wire (the shop sets each option per control):

      NUL × leader   [DC2]   % EOL  O1234 EOL  N10 G01 X1 EOL  …  % EOL   [DC4]   NUL × trailer

    * `leader`, `trailer` — NUL bytes before and after (tape feed; default 0);
    * `eol` — `:lf`, `:cr` or `:crlf` (default) ends each line;
    * `percent` — `:keep` (default): the `%` lines go on the wire and frame the program;
      `:strip`: they do not (controls that take `%` as a rewind stop of their own); DC2/DC4
      must then mark the program (`dc2_dc4: true`), and the `%` lines are put back on receive;
    * `dc2_dc4` — DC2 ("punch on") before the program and DC4 ("punch off") after it.

  Receiving is lenient where it cannot be wrong: NUL and DEL (tape feed, rub-out) and the flow
  control characters DC1/DC3 are never data; CR, LF and CR LF all end a line; whatever comes
  before the opening `%` is leader. A program is handed on whole — from its opening to its
  closing `%` (or DC2 to DC4) — or as an error: a control character or a byte over 0x7E inside
  it (`:bad_character`), DC4 before the closing `%` (`:incomplete`), more than `max_bytes`
  (`:too_long`; nothing more of it is kept). Plain RS-232 carries no check: what the codec hands
  on is what arrived, which is why a download is read back (docs/serial.md).

      iex> {:ok, f} = Vws.Links.RS232.Framing.new(eol: :crlf, leader: 2, dc2_dc4: true)
      iex> wire = IO.iodata_to_binary(Vws.Links.RS232.Framing.encode("%\\nO1\\nM30\\n%\\n", f))
      iex> wire
      <<0, 0, 0x12, "%\\r\\nO1\\r\\nM30\\r\\n%\\r\\n", 0x14>>
      iex> {events, _} = Vws.Links.RS232.Framing.decode(Vws.Links.RS232.Framing.decoder(f), wire)
      iex> events
      [{:program, "%\\nO1\\nM30\\n%\\n"}]
  """

  @dc1 0x11
  @dc2 0x12
  @dc3 0x13
  @dc4 0x14

  defstruct leader: 0, trailer: 0, eol: :crlf, percent: :keep, dc2_dc4: false

  @type t :: %__MODULE__{
          leader: non_neg_integer,
          trailer: non_neg_integer,
          eol: :lf | :cr | :crlf,
          percent: :keep | :strip,
          dc2_dc4: boolean
        }

  @type event :: {:program, binary} | {:error, :bad_character | :incomplete | :too_long}

  # the largest program a control stores (Vws.Links.DNC.Program.max_stored_bytes/0) and a margin
  @max_bytes 1_000_000
  @max_leader 10_000

  @doc "The framing from the shop's options; a bad one is said in words."
  @spec new(keyword) :: {:ok, t} | {:error, String.t()}
  def new(opts) when is_list(opts) do
    Enum.reduce_while(opts, {:ok, %__MODULE__{}}, fn {key, value}, {:ok, f} ->
      case set(f, key, value) do
        {:ok, f} -> {:cont, {:ok, f}}
        {:error, _} = error -> {:halt, error}
      end
    end)
    |> case do
      {:ok, %{percent: :strip, dc2_dc4: false}} ->
        {:error, "framing: percent: :strip needs dc2_dc4: true (nothing else marks a program)"}

      other ->
        other
    end
  end

  defp set(f, key, n) when key in [:leader, :trailer] and is_integer(n) and n in 0..@max_leader,
    do: {:ok, Map.put(f, key, n)}

  defp set(f, :eol, eol) when eol in [:lf, :cr, :crlf], do: {:ok, %{f | eol: eol}}
  defp set(f, :percent, p) when p in [:keep, :strip], do: {:ok, %{f | percent: p}}
  defp set(f, :dc2_dc4, on) when is_boolean(on), do: {:ok, %{f | dc2_dc4: on}}

  defp set(_f, key, value) when key in [:leader, :trailer],
    do:
      {:error,
       "framing: #{key} is a count of NUL bytes, 0 to #{@max_leader} (got #{inspect(value)})"}

  defp set(_f, :eol, value),
    do: {:error, "framing: eol is :lf, :cr or :crlf (got #{inspect(value)})"}

  defp set(_f, :percent, value),
    do: {:error, "framing: percent is :keep or :strip (got #{inspect(value)})"}

  defp set(_f, :dc2_dc4, value),
    do: {:error, "framing: dc2_dc4 is true or false (got #{inspect(value)})"}

  defp set(_f, key, _value),
    do:
      {:error,
       "framing: unknown option #{inspect(key)} (known: leader, trailer, eol, percent, dc2_dc4)"}

  @doc """
  The wire bytes of a program (DNC text: LF lines, the first and the last `%`). The caller has
  checked that the text holds no control character (`Vws.Links.DNC.Program.sendable?/1`).
  """
  @spec encode(binary, t) :: iodata
  def encode(text, %__MODULE__{} = f) do
    lines = Vws.Links.DNC.Program.from_text(text)
    lines = if f.percent == :strip, do: strip_percent(lines), else: lines
    eol = eol(f.eol)

    [
      :binary.copy(<<0>>, f.leader),
      if(f.dc2_dc4, do: <<@dc2>>, else: []),
      Enum.map(lines, &[&1, eol]),
      if(f.dc2_dc4, do: <<@dc4>>, else: []),
      :binary.copy(<<0>>, f.trailer)
    ]
  end

  defp strip_percent(["%" | rest]), do: strip_percent_end(rest)
  defp strip_percent(lines), do: strip_percent_end(lines)

  defp strip_percent_end(lines) do
    if List.last(lines) == "%", do: Enum.drop(lines, -1), else: lines
  end

  defp eol(:lf), do: "\n"
  defp eol(:cr), do: "\r"
  defp eol(:crlf), do: "\r\n"

  ## Receiving

  @doc "A decoder for programs framed by `framing`; option `max_bytes` bounds one program."
  @spec decoder(t, keyword) :: map
  def decoder(%__MODULE__{} = f, opts \\ []) do
    %{
      framing: f,
      max: Keyword.get(opts, :max_bytes, @max_bytes),
      phase: :idle,
      line: [],
      line_bytes: 0,
      lines: [],
      bytes: 0,
      damage: nil,
      after_cr: false
    }
  end

  @doc "Whether a program is being received (its opening seen, its end not yet)."
  @spec receiving?(map) :: boolean
  def receiving?(%{phase: phase}), do: phase == :in

  @doc """
  Takes received bytes: `{events, decoder}`, each event a whole program (`{:program, text}`) or
  the error that ended one. Never raises, whatever the bytes.
  """
  @spec decode(map, binary) :: {[event], map}
  def decode(state, bytes) when is_binary(bytes) do
    {events, state} = bytes(bytes, state, [])
    {Enum.reverse(events), state}
  end

  defp bytes(<<>>, s, acc), do: {acc, s}

  # never data: tape feed, rub-out, flow control
  defp bytes(<<b, rest::binary>>, s, acc) when b in [0, 0x7F, @dc1, @dc3],
    do: bytes(rest, s, acc)

  defp bytes(<<@dc2, rest::binary>>, s, acc) do
    s =
      if s.framing.dc2_dc4 and s.framing.percent == :strip and s.phase == :idle,
        do: start(s, []),
        else: s

    bytes(rest, %{s | after_cr: false}, acc)
  end

  defp bytes(<<@dc4, rest::binary>>, s, acc) do
    cond do
      not s.framing.dc2_dc4 or s.phase == :idle ->
        bytes(rest, idle(s), acc)

      s.framing.percent == :strip ->
        s = if s.line_bytes > 0, do: end_line(s), else: s
        bytes(rest, idle(s), [finish(s, ["%" | Enum.reverse(s.lines)] ++ ["%"]) | acc])

      true ->
        # punch off before the closing %: the program was cut short
        bytes(rest, idle(s), [{:error, :incomplete} | acc])
    end
  end

  defp bytes(<<?\n, rest::binary>>, %{after_cr: true} = s, acc),
    do: bytes(rest, %{s | after_cr: false}, acc)

  defp bytes(<<b, rest::binary>>, s, acc) when b in [?\r, ?\n] do
    {s, acc} = line_end(s, acc)
    bytes(rest, %{s | after_cr: b == ?\r}, acc)
  end

  # before a program: only a line that is "%" opens one (its first byte is all that is kept)
  defp bytes(<<b, rest::binary>>, %{phase: :idle} = s, acc) do
    s = if s.line_bytes == 0, do: %{s | line: [b], line_bytes: 1}, else: %{s | line_bytes: 2}
    bytes(rest, %{s | after_cr: false}, acc)
  end

  defp bytes(<<b, rest::binary>>, s, acc) do
    s = %{s | after_cr: false}
    s = if b < 0x20 or b > 0x7E, do: %{s | damage: s.damage || :bad_character}, else: s
    bytes(rest, add(s, b), acc)
  end

  defp add(s, b) do
    bytes = s.bytes + 1

    if bytes > s.max or s.damage == :too_long,
      # nothing more is kept; only whether the line is "%" (the program's end) is
      do: %{
        s
        | damage: :too_long,
          line: too_long_line(s, b),
          lines: [],
          bytes: bytes,
          line_bytes: s.line_bytes + 1
      },
      else: %{s | line: [s.line | [b]], line_bytes: s.line_bytes + 1, bytes: bytes}
  end

  defp too_long_line(%{line_bytes: 0}, b), do: [b]
  defp too_long_line(_s, _b), do: "xx"

  # a line ended: in :idle, "%" opens a program (:keep); inside one, "%" closes it
  defp line_end(%{phase: :idle} = s, acc) do
    s =
      if s.framing.percent == :keep and s.line_bytes == 1 and s.line == [?%],
        do: start(s, ["%"]),
        else: %{s | line: [], line_bytes: 0}

    {s, acc}
  end

  defp line_end(s, acc) do
    line = IO.iodata_to_binary(s.line)

    if s.framing.percent == :keep and line == "%" do
      s = %{s | lines: if(s.damage == :too_long, do: [], else: ["%" | s.lines])}
      {idle(s), [finish(s, Enum.reverse(s.lines)) | acc]}
    else
      {end_line(s), acc}
    end
  end

  defp end_line(s) do
    line = IO.iodata_to_binary(s.line)
    # the LF counts toward the program's size too
    bytes = s.bytes + 1

    cond do
      s.damage == :too_long -> %{s | line: [], line_bytes: 0}
      bytes > s.max -> %{s | damage: :too_long, lines: [], line: [], line_bytes: 0, bytes: bytes}
      true -> %{s | lines: [line | s.lines], line: [], line_bytes: 0, bytes: bytes}
    end
  end

  defp start(s, lines),
    do: %{
      s
      | phase: :in,
        lines: lines,
        line: [],
        line_bytes: 0,
        bytes: 2 * length(lines),
        damage: nil
    }

  defp finish(%{damage: nil}, lines), do: {:program, Enum.map_join(lines, "", &[&1, ?\n])}
  defp finish(%{damage: damage}, _lines), do: {:error, damage}

  defp idle(s),
    do: %{s | phase: :idle, lines: [], line: [], line_bytes: 0, bytes: 0, damage: nil}
end
