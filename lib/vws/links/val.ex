defmodule Vws.Links.VAL do
  @moduledoc """
  The VAL II supervisory logical-unit layer, CEC side (seed §4.3–4.4, PROTOCOLS.md §3): monitor
  commands to a Unimation VAL II controller over a `Vws.Links.DDCMP` link.

  One process per robot controller, and per wire: it dials the controller, runs the DDCMP
  protocol itself (`Vws.Links.DDCMP.Protocol`, role `:active`: the CEC sends STRT) and speaks VAL data
  messages (`Vws.Links.VAL.Message`) over it — the link's news reaches the logical units in the order
  it happened, in the same process:

    * **LUN 2, monitor input/output.** After start-up the monitor sends a READ — the prompt. Only
      then does the CEC send one monitor command, as a LUN 2 WRITE (that is its reply to the
      READ). The monitor answers with a LUN 2 WRITE whose text begins with a number (`0` normal,
      negative: an error code, see `parse_response/1`); the CEC REPLYs to it, and the monitor
      prompts again.
    * **LUN 3, monitor asynchronous output.** WRITEs whose qualifier is the message code: MOTION
      BEGIN, MOTION COMPLETE, PROGRAM START, PROGRAM COMPLETE, ERROR. The CEC REPLYs to each at
      once (same code, no text).
    * **LUN 1, short status.** WRITEs of a terse status text; the CEC keeps the latest (see
      `info/1`) and REPLYs.

  ## Numbers

  On LUNs 1 and 2 the qualifier of a message a unit initiates is its number (1–255, counting
  on), and the CEC's answer carries the same number: the command answering a prompt (READ)
  carries the prompt's number, a REPLY the number of what it replies to (on LUN 3 the qualifier
  is the message code, echoed the same way). A controller can so tell an answer from one left
  over from before a restart of the link, and never obeys a command that answers an old prompt.
  (Our decision, PROTOCOLS.md §3 leaving the qualifier of LUNs 1 and 2 open.)

  The rule of seed §4.3.3: VAL II initiates everything, and after each message a logical unit
  initiates, the CEC replies before that unit sends again — so a LUN waits for its reply while the
  other LUNs carry on (LUN 3 reports motion while LUN 2 answers a `WHERE`). This process replies
  to every LUN-initiated message as soon as it is handled and never sends a command without an
  outstanding prompt.

  ## Requests

  `request/3` sends one monitor command and waits for what its caller says it waits for
  (ROBOT knows that from the command it parsed); `command/3`, `motion/3` and `execute/3` are the
  same for a text, a `DO` instruction and a program name. A command waits

    * for its numbered response (`WHERE`, `SPEED 50`, …) → `{:ok, text}`;
    * a motion instruction, `DO …`, also for MOTION COMPLETE on LUN 3 (seed §4.4: the CEC sends no
      new `DO` until the previous one has completed); a second `DO` waits for that;
    * `EXECUTE name` also for PROGRAM COMPLETE.

  A negative response, or a LUN 3 ERROR while the motion or program runs, ends the request
  `{:error, {code, text}}`. Requests wait (without being sent) while the link starts up or
  restarts by itself, or the prompt has not come; one whose time runs out while waiting is never
  sent, and one whose caller has gone is dropped. A request already sent when the link goes down
  or the controller restarts ends `{:error, {:link_down, reason}}` or `{:error, :peer_restarted}`
  and is **never re-sent**: a robot move is physical. When the link's transport is gone (the
  link is down `:closed` or `{:transport, _}`, and dials again), the requests waiting end
  `{:error, {:link_down, reason}}`, and so does every request made until the link is up again:
  a move is never held back to go whenever the robot is reachable again.

      {:ok, val} = Vws.Links.VAL.start_link(ddcmp: [endpoint: "tcp://robot:2000"])
      :ok = Vws.Links.VAL.motion(val, "DO MOVE SAFE", 60_000)
      {:ok, where} = Vws.Links.VAL.command(val, "WHERE", 5_000)
      {:ok, %{world: [x, y, z, o, a, t], joints: joints}} = Vws.Links.VAL.parse_where(where)

  ## Options

    * `:name` — registered name of the process
    * `:ddcmp` — options for the link, as `Vws.Links.DDCMP`'s: `:endpoint` (required; dialled again
      with back-off whenever the controller goes away), `:window`, `:rep_timeout`, `:backoff`,
      `:workstation`, …; `:role` is set here.
    * `:id` — the child spec's id.

  Checked by `start_link/1` (`Vws.Options`): an unknown option or a bad value raises
  `Vws.Options.Error` naming it.

  ## Telemetry

  The link's own events are `Vws.Links.DDCMP`'s (`[:vws, :ddcmp, …]`, `link` the name of this process).

    * `[:vws, :val, :message]` — `%{bytes}`, `%{name, workstation, direction: :in | :out, lun,
      function, qualifier}`, every VAL data message
    * `[:vws, :val, :request_finished]` — `%{duration}` (native), `%{name, workstation, text, result}`
    * `[:vws, :val, :async]` — `%{count: 1}`, `%{name, workstation, code, text}`, every LUN 3 message

  `workstation` is the id in a `Vws.CEC.Workstation` name (`Vws.Names.id_of/1`), else nil.
  """

  @type val :: GenServer.server()
  @type error ::
          {:error,
           {integer, String.t()}
           | :timeout
           | :peer_restarted
           | :no_response
           | {:link_down, term}
           | {:bad_response, String.t()}
           | {:bad_command, Vws.Links.VAL.Error.t()}}

  @schema [
    name: [type: :any],
    id: [type: :any],
    ddcmp: [type: :keyword_list, required: true]
  ]

  @doc false
  def child_spec(opts) do
    %{
      id: Keyword.get(opts, :id, __MODULE__),
      start: {__MODULE__, :start_link, [opts]},
      shutdown: 5_000
    }
  end

  @doc "Starts the process for one VAL II wire. See the module doc for options."
  @spec start_link(keyword) :: :gen_statem.start_ret()
  def start_link(opts) do
    opts = Vws.Options.validate!(opts, @schema, "VAL")
    ddcmp = Keyword.fetch!(opts, :ddcmp)

    unless Keyword.has_key?(ddcmp, :endpoint),
      do: raise(ArgumentError, "Vws.Links.VAL needs ddcmp: [endpoint: …]")

    opts =
      Keyword.put(opts, :ddcmp, Vws.Links.DDCMP.validate!(Keyword.put(ddcmp, :role, :active)))

    case Keyword.get(opts, :name) do
      nil ->
        :gen_statem.start_link(Vws.Links.VAL.Connection, opts, [])

      name when is_atom(name) ->
        :gen_statem.start_link({:local, name}, Vws.Links.VAL.Connection, opts, [])

      name ->
        :gen_statem.start_link(name, Vws.Links.VAL.Connection, opts, [])
    end
  end

  @doc """
  Sends one monitor command and waits for its outcome (see "Requests"): `{:ok, response_text}`
  (the text after the leading `0`), or an error. `timeout` covers the wait for the prompt too.
  """
  @spec command(val, String.t(), timeout) :: {:ok, String.t()} | error
  def command(val, text, timeout \\ 10_000) when is_binary(text) do
    request(val, {waits_for(text), text}, timeout)
  end

  @doc """
  Sends one monitor command `text` and waits for its response and then for `wait`:
  `:response` (nothing more), `:motion_complete` (a `DO` instruction) or `:program_complete`
  (`EXECUTE`). The caller knows what it asked for; the text is not read again to learn it. A
  `DO` or `EXECUTE` text with `:response` raises `ArgumentError`: it would let a second motion go
  before the first completed.
  """
  @spec request(val, {:response | :motion_complete | :program_complete, String.t()}, timeout) ::
          {:ok, String.t()} | error
  def request(val, {wait, text}, timeout)
      when wait in [:response, :motion_complete, :program_complete] and is_binary(text) do
    if wait == :response and waits_for(text) != :response,
      do: raise(ArgumentError, "#{inspect(text)} waits for more than its response")

    # the process honours the caller's deadline (a command is never sent after it); an answer
    # after it never reaches the caller (Vws.Links.Connection)
    case Vws.Links.Connection.call(val, {:request, text, wait}, timeout) do
      {:ok, result} -> result
      {:error, :timeout} -> {:error, :timeout}
      # not running, or ended during the call: the command's fate is unknown, never a crash here
      {:error, {:exit, reason}} -> {:error, {:link_down, reason}}
    end
  end

  @doc "Runs the VAL II program `name` (`EXECUTE name`) and waits for PROGRAM COMPLETE."
  @spec execute(val, String.t(), timeout) :: {:ok, String.t()} | error
  def execute(val, name, timeout \\ 600_000) when is_binary(name),
    do: request(val, {:program_complete, "EXECUTE " <> name}, timeout)

  @doc """
  Runs a motion instruction (`"DO MOVE SAFE"`) and waits for MOTION COMPLETE. Raises
  `ArgumentError` for text that is not a `DO` instruction.
  """
  @spec motion(val, String.t(), timeout) :: :ok | error
  def motion(val, text, timeout \\ 60_000) when is_binary(text) do
    unless waits_for(text) == :motion_complete,
      do: raise(ArgumentError, "not a DO instruction: #{inspect(text)}")

    case request(val, {:motion_complete, text}, timeout) do
      {:ok, _} -> :ok
      error -> error
    end
  end

  @doc """
  Re-initialises the link between commands, as the seed's ROBOT program does (seed §4.3.2): the
  CEC sends STRT, and the next command waits for the start-up and a fresh prompt. Refused with
  `{:error, :busy}` while a command or motion is in flight.
  """
  @spec reinitialise(val) :: :ok | {:error, :busy}
  def reinitialise(val), do: :gen_statem.call(val, :reinitialise)

  @doc """
  What the layer is doing: `state` `{lun2, activity}` — `lun2` is `:down` (link not running),
  `:idle` (waiting for the prompt), `:ready` or `:busy` (a command awaits its response);
  `activity` is `:still` or `:moving` (a `DO` or program in flight) — and `line` (the DDCMP
  protocol's state and numbers, as `Vws.Links.DDCMP.info/1`), `prompt` (`{number, text}` of the outstanding prompt), `short_status` (LUN 1's
  latest), `last_async` (the latest LUN 3 messages, `{code, text}`, oldest first), `queued`,
  `in_flight` (texts), `counts`.
  """
  @spec info(val) :: map
  def info(val), do: :gen_statem.call(val, :info)

  @doc "True when the link is up and the monitor has prompted: the next command goes at once."
  @spec ready?(val) :: boolean
  def ready?(val), do: match?(%{state: {:ready, _}}, info(val))

  @doc """
  Splits a numbered monitor response: `0` (or any non-negative number) is normal, a negative
  number is an error code.

      iex> Vws.Links.VAL.parse_response("0")
      {:ok, ""}
      iex> Vws.Links.VAL.parse_response("0 SPEED 50")
      {:ok, "SPEED 50"}
      iex> Vws.Links.VAL.parse_response("-602 LOCATION OUT OF REACH")
      {:error, {-602, "LOCATION OUT OF REACH"}}
      iex> Vws.Links.VAL.parse_response("HELLO")
      {:error, {:bad_response, "HELLO"}}
  """
  @spec parse_response(String.t()) ::
          {:ok, String.t()} | {:error, {integer, String.t()} | {:bad_response, String.t()}}
  def parse_response(text) do
    case Regex.run(~r/\A\s*([+-]?\d+)(?:[ \t]*\r?\n?)?(.*)\z/s, text) do
      [_, number, rest] ->
        case String.to_integer(number) do
          n when n >= 0 -> {:ok, String.trim_trailing(rest)}
          n -> {:error, {n, String.trim(rest)}}
        end

      nil ->
        {:error, {:bad_response, text}}
    end
  end

  @doc """
  The 12 numbers of a `WHERE` response: world `x y z θ A T` and joints `j1 … j6` (j3 the boom
  extension in mm). Every whitespace-separated token that is a number counts; labels are skipped.

      iex> Vws.Links.VAL.parse_where("X Y Z O A T\\n1 2 3 90 -90 0\\nJT1 JT2 JT3 JT4 JT5 JT6\\n5 6 700 8 9 10")
      {:ok, %{world: [1.0, 2.0, 3.0, 90.0, -90.0, 0.0], joints: [5.0, 6.0, 700.0, 8.0, 9.0, 10.0]}}
  """
  @spec parse_where(String.t()) ::
          {:ok, %{world: [float], joints: [float]}} | {:error, {:bad_response, String.t()}}
  def parse_where(text) do
    numbers = for token <- String.split(text), {v, ""} <- [Float.parse(token)], do: v

    case numbers do
      [_, _, _, _, _, _, _, _, _, _, _, _] ->
        {world, joints} = Enum.split(numbers, 6)
        {:ok, %{world: world, joints: joints}}

      _ ->
        {:error, {:bad_response, text}}
    end
  end

  # what a text command waits for after its response (for callers that hold only the text)
  defp waits_for(text) do
    case text |> String.trim_leading() |> String.upcase() do
      "DO " <> _ -> :motion_complete
      "EXECUTE " <> _ -> :program_complete
      _ -> :response
    end
  end
end
