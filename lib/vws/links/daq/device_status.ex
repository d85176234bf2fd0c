defmodule Vws.Links.DAQ.DeviceStatus do
  @moduledoc """
  The device-status texts of PROTOCOLS.md §1 (seed Table 2, App. I G) built from one poll of
  DAQ #1. Pure. VWS_STATUS writes them to mailbox locations 1–5 and 7 after every poll; SUN_COMM
  answers the WC's status commands with them.

  | location | status command | text |
  |----------|----------------|------|
  | 1 | `GRIPPER`   | `GRIPPER IS OPEN AND INDEXER ROTATED 90 DEG`, `FINGERS ARE 12.5 MM APART AND INDEXER ROTATED 0 DEG` |
  | 2 | `TABLE`     | `TABLE IN PARK POSITION`, `TABLE NOT IN PARK POSITION` |
  | 3 | `VISE`      | `VISE JAWS ARE 50.0 MM APART AND VISE IS LOCKED PART IN VISE`, `… AND VISE IS UNLOCKED PART NOT IN VISE` |
  | 4 | `TRAYS`     | `TRAY #1 IN POSITION TRAY #2 NOT IN POSITION` |
  | 5 | `VACUUM`    | `VACUUM IS ON`, `VACUUM IS OFF` |
  | 7 | `CHANGER_1` | `CHANGER_1 FINGERS RELEASED`, `CHANGER_1 FINGERS DID NOT RELEASE` |

  Decisions: distances in millimetres with one decimal, forces in whole newtons; "locked" means
  the vise force gauge reads at least the minimum clamping force (option `:min_force_n`, default
  800 N); the indexer is "ROTATED n DEG" only while exactly one of its four position switches is
  closed (`INDEXER BETWEEN POSITIONS` when none, `INDEXER SWITCHES DISAGREE` when several).

  A text is never built from a reading that is not there: a sensor that reads the DMM's
  overload value gives `NO DATA (<DEVICE> SENSOR CH nnn OPEN CIRCUIT)`, a sensor that is not
  wired `NO DATA (<DEVICE> NOT WIRED TO DAQ #1)`, and when the DAQ does not answer VWS_STATUS
  writes `no_data/1` texts instead of keeping the last ones.

      iex> r = %Vws.Links.DAQ.Readings{values: %{vise_jaw_mm: 49.96, vise_force_n: 1998.7,
      ...>   vise_part_present: true, vise_fully_open: false}}
      iex> Vws.Links.DAQ.DeviceStatus.vise(r)
      "VISE JAWS ARE 50.0 MM APART AND VISE IS LOCKED PART IN VISE"
      iex> Vws.Links.DAQ.DeviceStatus.no_data("DAQ #1 NOT ANSWERING")
      "NO DATA (DAQ #1 NOT ANSWERING)"
  """

  alias Vws.Links.DAQ.Readings

  @min_force_n 800

  @locations [gripper: 1, table: 2, vise: 3, trays: 4, vacuum: 5, changer_1: 7]
  @indexer [indexer_0: 0, indexer_90: 90, indexer_180: 180, indexer_270: 270]
  @gripper_signals [:gripper_fully_open, :gripper_finger_mm | Keyword.keys(@indexer)]

  @doc "The mailbox location of each device text (1–5, 7)."
  @spec locations() :: keyword(1..14)
  def locations, do: @locations

  @doc "Every device text of one poll, by mailbox location. Options: `:min_force_n`."
  @spec texts(Readings.t(), keyword) :: %{pos_integer => String.t()}
  def texts(%Readings{} = r, opts \\ []), do: :maps.from_list(text_list(r, opts))

  @doc "`texts/2` as a list `[{location, text}]`, in the order of the locations."
  @spec text_list(Readings.t(), keyword) :: [{pos_integer, String.t()}]
  def text_list(%Readings{} = r, opts \\ []),
    do: for({device, loc} <- @locations, do: {loc, text(device, r, opts)})

  @doc "The text of one device (`:gripper`, `:table`, `:vise`, `:trays`, `:vacuum`, `:changer_1`)."
  @spec text(atom, Readings.t(), keyword) :: String.t()
  def text(:gripper, r, _opts), do: gripper(r)
  def text(:table, r, _opts), do: table(r)
  def text(:vise, r, opts), do: vise(r, opts)
  def text(:trays, r, _opts), do: trays(r)
  def text(:vacuum, r, _opts), do: vacuum(r)
  def text(:changer_1, r, _opts), do: changer_1(r)

  @doc "The text every location gets when there is no fresh reading: `NO DATA (<reason>)`."
  @spec no_data(String.t()) :: String.t()
  def no_data(reason), do: "NO DATA (#{reason})"

  @doc "GRIPPER: the fingers (open, or how far apart) and the indexer position."
  @spec gripper(Readings.t()) :: String.t()
  def gripper(r) do
    with {:ok, [open, mm | indexer]} <-
           fetch(r, "GRIPPER", @gripper_signals) do
      fingers = if open, do: "GRIPPER IS OPEN", else: "FINGERS ARE #{mm(mm)} MM APART"
      fingers <> " AND " <> indexer_text(indexer)
    end
  end

  @doc "The indexer's position from its four switches, in degrees, or why there is none."
  @spec indexer(Readings.t()) :: {:ok, 0 | 90 | 180 | 270} | {:error, :between | :disagree}
  def indexer(r) do
    case for({signal, deg} <- @indexer, Readings.get(r, signal) == true, do: deg) do
      [deg] -> {:ok, deg}
      [] -> {:error, :between}
      _ -> {:error, :disagree}
    end
  end

  defp indexer_text(states) do
    case for({true, {_s, deg}} <- :lists.zip(states, @indexer), do: deg) do
      [deg] -> "INDEXER ROTATED #{deg} DEG"
      [] -> "INDEXER BETWEEN POSITIONS"
      _ -> "INDEXER SWITCHES DISAGREE"
    end
  end

  @doc "TABLE: the park switch."
  @spec table(Readings.t()) :: String.t()
  def table(r) do
    with {:ok, [park]} <- fetch(r, "TABLE", [:table_park]) do
      if park, do: "TABLE IN PARK POSITION", else: "TABLE NOT IN PARK POSITION"
    end
  end

  @doc "VISE: the jaw opening, locked (force at least `:min_force_n`) or not, part present or not."
  @spec vise(Readings.t(), keyword) :: String.t()
  def vise(r, opts \\ []) do
    min = Keyword.get(opts, :min_force_n, @min_force_n)

    with {:ok, [jaw, force, part]} <-
           fetch(r, "VISE", [:vise_jaw_mm, :vise_force_n, :vise_part_present]) do
      locked = if force >= min, do: "LOCKED", else: "UNLOCKED"
      part = if part, do: "PART IN VISE", else: "PART NOT IN VISE"
      "VISE JAWS ARE #{mm(jaw)} MM APART AND VISE IS #{locked} #{part}"
    end
  end

  @doc "TRAYS: the in-position switch of each tray."
  @spec trays(Readings.t()) :: String.t()
  def trays(r) do
    with {:ok, [t1, t2]} <- fetch(r, "TRAYS", [:tray1_in, :tray2_in]) do
      "TRAY #1 #{position(t1)} TRAY #2 #{position(t2)}"
    end
  end

  defp position(true), do: "IN POSITION"
  defp position(false), do: "NOT IN POSITION"

  @doc "VACUUM: the pressure switch (the motor may run and still draw no vacuum)."
  @spec vacuum(Readings.t()) :: String.t()
  def vacuum(r) do
    with {:ok, [on]} <- fetch(r, "VACUUM", [:vacuum_on]) do
      if on, do: "VACUUM IS ON", else: "VACUUM IS OFF"
    end
  end

  @doc "CHANGER_1: its fingers-released switch, when one is wired (see `Vws.Links.DAQ` `:switches`)."
  @spec changer_1(Readings.t()) :: String.t()
  def changer_1(r) do
    with {:ok, [released]} <- fetch(r, "CHANGER_1", [:changer1_released]) do
      if released,
        do: "CHANGER_1 FINGERS RELEASED",
        else: "CHANGER_1 FINGERS DID NOT RELEASE"
    end
  end

  @doc "Millimetres as the texts write them: one decimal, never negative (noise around 0)."
  @spec mm(number) :: String.t()
  def mm(value) do
    # `if` rather than max/2: max(-0.0, 0.0) is -0.0, which prints "-0.0"
    value = if value > 0, do: value * 1.0, else: 0.0
    :erlang.float_to_binary(value, decimals: 1)
  end

  @doc "Newtons as the texts write them: a whole number, never negative."
  @spec newtons(number) :: String.t()
  def newtons(value), do: if(value > 0, do: round(value), else: 0) |> Integer.to_string()

  defp fetch(r, device, signals) do
    case Readings.fetch(r, signals) do
      {:ok, values} -> {:ok, values}
      {:not_wired, _signal} -> no_data("#{device} NOT WIRED TO DAQ #1")
      {:open_circuit, ch} -> no_data("#{device} SENSOR CH #{ch} OPEN CIRCUIT")
    end
  end
end
