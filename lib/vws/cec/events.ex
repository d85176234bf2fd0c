defmodule Vws.CEC.Events do
  @moduledoc """
  The seed's EVENTs (§2.3.4) as pub/sub on `Registry`: CREATE EVENT, CAUSE EVENT and ON EVENT.

  In the 1988 CEC an EVENT was a system variable that one partition incremented with
  `CAUSE EVENT` and another waited on with `ON EVENT`. Here an event belongs to a workstation and
  has a name (an atom such as `:robot` or `:ok_to_proceed`):

    * `create/2` declares it (CREATE EVENT); causing an event that was never created is an error,
      as it was on the HP-9000;
    * `subscribe/2` is ON EVENT: the calling process receives every later cause;
    * `cause/3` is CAUSE EVENT: it increments the event's count and sends every subscriber

          {:vws_event, workstation, event, payload}

      which is the one message shape of this module;
    * `count/2` queries the variable, so a process that starts late (SUN_COMM waiting for
      OK_TO_PROCEED) can see that the event already happened.

  Subscriptions live in the node-wide duplicate-key registry `Vws.CEC.Events`; counts live in the
  workstation's mailbox table, so they survive the restart of any partition.

      iex> ws = "doc-events"
      iex> {:ok, _} = Vws.CEC.Mailbox.Owner.start_link(workstation: ws)
      iex> :ok = Vws.CEC.Events.create(ws, :gripper)
      iex> :ok = Vws.CEC.Events.subscribe(ws, :gripper)
      iex> :ok = Vws.CEC.Events.cause(ws, :gripper, 4)
      iex> receive do
      ...>   {:vws_event, ^ws, :gripper, n} -> n
      ...> end
      4
      iex> Vws.CEC.Events.count(ws, :gripper)
      1
  """

  @typedoc "A workstation id."
  @type workstation :: term
  @type event :: atom

  @doc "CREATE EVENT: declares `event` for the workstation (idempotent)."
  @spec create(workstation, event) :: :ok
  def create(ws, event) when is_atom(event) do
    :ets.insert_new(Vws.Names.mailbox_table(ws), {{:event, event}, 0})
    :ok
  end

  @doc "ON EVENT: the calling process receives `{:vws_event, ws, event, payload}` for each cause."
  @spec subscribe(workstation, event) :: :ok
  def subscribe(ws, event) do
    {:ok, _} = Registry.register(__MODULE__, {ws, event}, nil)
    :ok
  end

  @doc "Stops the calling process's subscription."
  @spec unsubscribe(workstation, event) :: :ok
  def unsubscribe(ws, event), do: Registry.unregister(__MODULE__, {ws, event})

  @doc """
  CAUSE EVENT: counts the event and sends `payload` to its subscribers.

  Returns `{:error, :no_such_event}` for an event that was not created.
  """
  @spec cause(workstation, event, term) :: :ok | {:error, :no_such_event}
  def cause(ws, event, payload \\ nil) do
    try do
      :ets.update_counter(Vws.Names.mailbox_table(ws), {:event, event}, 1)

      Registry.dispatch(__MODULE__, {ws, event}, fn entries ->
        for {pid, _} <- entries, do: send(pid, {:vws_event, ws, event, payload})
      end)

      Vws.Telemetry.execute([:vws, :events, :caused], %{count: 1}, %{
        workstation: ws,
        event: event
      })

      :ok
    rescue
      ArgumentError -> {:error, :no_such_event}
    end
  end

  @doc """
  Sends `payload` to the event's subscribers as `{:vws_event, workstation, event, payload}`, like
  `cause/3`, but without counting it or emitting telemetry: for notices that may come many times
  a second (`:mailbox`, each change of a mailbox location, which `Vws.Ops.MTConnect.Agent` records).
  Needs no `create/2`.
  """
  @spec notify(workstation, event, term) :: :ok
  def notify(ws, event, payload) do
    Registry.dispatch(__MODULE__, {ws, event}, fn entries ->
      for {pid, _} <- entries, do: send(pid, {:vws_event, ws, event, payload})
    end)
  end

  @doc "How many times the event has been caused; `nil` when it was never created."
  @spec count(workstation, event) :: non_neg_integer | nil
  def count(ws, event) do
    case :ets.lookup(Vws.Names.mailbox_table(ws), {:event, event}) do
      [{_, n}] -> n
      [] -> nil
    end
  end

  @doc "The events created for a workstation with their counts."
  @spec list(workstation) :: [{event, non_neg_integer}]
  def list(ws) do
    Vws.Names.mailbox_table(ws)
    |> :ets.match({{:event, :"$1"}, :"$2"})
    |> Enum.map(fn [e, n] -> {e, n} end)
    |> Enum.sort()
  end
end
