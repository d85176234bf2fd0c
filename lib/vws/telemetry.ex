defmodule Vws.Telemetry do
  @moduledoc """
  The one seam between VWS and telemetry, with the contract of the `:telemetry` library
  (`execute/3`, `span/3`, `attach/4`, `attach_many/4`, `detach/1`).

  When `:telemetry` is loaded (a deployment that has the hex package), every call is delegated to
  it. Otherwise handlers are kept here, in `:persistent_term` (attaching is rare, emitting is
  frequent), and called synchronously in the emitting process exactly as `:telemetry` would; a
  handler that raises is detached and logged, as `:telemetry` does.

  ## Events

  Spans emit `prefix ++ [:start]` (measurements `%{system_time, monotonic_time}`),
  `prefix ++ [:stop]` (`%{duration, monotonic_time}`) and `prefix ++ [:exception]`
  (`%{duration, monotonic_time}`, metadata adds `:kind, :reason, :stacktrace`).

  | event | measurements | metadata |
  |-------|--------------|----------|
  | `[:vws, :sun_comm, :string_received]` | `bytes` | `workstation, sequence, commands` |
  | `[:vws, :sun_comm, :string_rejected]` | `bytes` | `workstation, reason` |
  | `[:vws, :sun_comm, :retransmission]` | `count` | `workstation, sequence` |
  | `[:vws, :sun_comm, :reply_sent]` | `bytes` | `workstation, kind` |
  | `[:vws, :sun_comm, :rule_broken]` | `count` | `workstation, sequence, rule` |
  | `[:vws, :sun_comm, :wc_connected]` / `:wc_disconnected` | `count` | `workstation, peer` |
  | `[:vws, :sun_comm, :nc_line]` | `bytes` | `workstation, direction` |
  | `[:vws, :partition, :command_dispatched]` | `count` | `workstation, partition, command, text` |
  | `[:vws, :partition, :command, :start / :stop / :exception]` | span | `workstation, partition, command, text` (+ `result` on stop) |
  | `[:vws, :partition, :command_finished]` | `duration` (native) | `workstation, partition, command, status` |
  | `[:vws, :events, :caused]` | `count` | `workstation, event` |
  | `[:vws, :val, :message]` | `bytes` | `name, workstation, direction, lun, function, qualifier, text` |
  | `[:vws, :val, :request_finished]` | `duration` (native) | `name, workstation, text, result` |
  | `[:vws, :val, :async]` | `count` | `name, workstation, code, text` (every LUN 3 message) |
  | `[:vws, :ddcmp, :frame_sent]` / `:frame_received` | `count` | `link, workstation` + the frame's fields |
  | `[:vws, :ddcmp, :nak]` | `count` | `link, workstation, direction, reason, resp` |
  | `[:vws, :ddcmp, :rep]` | `count` | `link, workstation, direction, num` |
  | `[:vws, :ddcmp, :retransmission]` | `count, bytes` | `link, workstation, num` |
  | `[:vws, :ddcmp, :receive_error]` | `count` | `link, workstation, reason, num` |
  | `[:vws, :ddcmp, :state_change]` | `count` | `link, workstation, from, to` |
  | `[:vws, :ddcmp, :link_down]` | `count` | `link, workstation, reason` |
  | `[:vws, :ddcmp, :connect_failed]` | `count, retry_in` (ms) | `link, workstation, endpoint, reason` |
  | `[:vws, :dnc, :connected]` / `:disconnected` | `count` | `link, workstation, role, peer` (+ `reason`) |
  | `[:vws, :dnc, :connect_failed]` | `count, retry_in` (ms) | `link, workstation, role, endpoint, reason` |
  | `[:vws, :dnc, :block_sent]` | `bytes` | `link, workstation, role, block, retransmission` |
  | `[:vws, :dnc, :block_received]` | `bytes` | `link, workstation, role, block` |
  | `[:vws, :monarch, :request_again]` | `count` | `workstation, operation, reason` |
  | `[:vws, :dnc, :retry]` | `count` | `link, workstation, role, kind, block` |
  | `[:vws, :dnc, :transmission]` | `duration, blocks, bytes` | `link, workstation, role, direction, result` |
  | `[:vws, :dnc, :progress]` | `blocks, bytes, program_bytes, chars_per_s, retries` | `link, workstation, role, program, direction, operation, total_blocks, total_bytes, total_program_bytes, eta_s, ended` (false, or `:ok`/the failure; an NC program's transfer: every block, and its end; `Vws.DNC.Progress`) |
  | `[:vws, :monarch, :program_received]` | `bytes` | `workstation, program, from` (`:machine`), `result`: a program the operator sent from the machine |
  | `[:vws, :web, :request]` | `duration, bytes` | `method, path, status, port` |
  | `[:vws, :hpib, :connected]` / `:disconnected` | `count` | `bus, address, endpoint` (+ `reason`) |
  | `[:vws, :hpib, :timeout]` | `count` | `bus, address, endpoint, commands` |
  | `[:vws, :hpib, :retry]` | `count` | `bus, address, endpoint, commands, reason, try` |
  | `[:vws, :hpib, :connect_failed]` | `count, retry_in` (ms) | `bus, address, endpoint, reason` |
  | `[:vws, :vws_status, :poll]` | `started_at, lateness, duration, handling` (µs) | `workstation, seq, result` |
  | `[:vws, :vws_status, :missed]` | `count` | `workstation, reason` |
  | `[:vws, :vws_status, :stale]` | `count` | `workstation, reason` |
  | `[:vws, :vws_status, :actuation_retry]` | `count` | `workstation, reason, try` |
  | `[:vws, :partition, :cleaned_up]` | `count` | `workstation, partition, command, text, status`: the safe clean-up of a command a restart interrupted |
  | `[:vws, :hydraulic_controller, :relay_corrected]` | `count` | `device`: a DAQ #2 slot read back not as intended, set right |
  | `[:vws, :interlock, :acquired]` | `wait_ms, tries` | `workstation, volume, holder, reason` |
  | `[:vws, :interlock, :refused]` | `wait_ms, tries` | `workstation, volume, holder, reason, why` |
  | `[:vws, :interlock, :released]` | `count` | `workstation, volume, holder, reason` (`:all` or one) |
  | `[:vws, :sim, :plant, :actuator]` | `count` | `workstation, daq, channel, signal, action` (`:close`/`:open`): every relay a simulated DAQ wrote |
  | `[:vws, :sim, :val2, :command]` | `count` | `workstation, text`: every monitor command the simulated VAL II obeyed |
  | `[:vws, :sim, :ge2000, :command]` | `bytes` | `workstation, operation, name, alarm`: every S command the simulated GE-2000 took |
  | `[:vws, :sim, :ge2000, :cycle_start]` | `count` | `workstation, program`: every cycle the simulated GE-2000 started |
  | `[:vws, :sim, :ge2000, :drip_feed]` | `bytes` | `workstation, program, result, underruns`: a drip feed the simulated GE-2000 ran to its end |

  `workstation` is the id of the workstation the event belongs to (nil for a link or simulator
  that serves none). The `[:vws, :sim, …]` events come from the simulators: what the simulated
  equipment physically did, for tests that count executions. `attach_default_handler/0` logs
  all of them with `Logger`.
  """

  require Logger

  @type event_name :: [atom, ...]
  @type handler_function :: (event_name, map, map, term -> any)

  @events [
    [:vws, :sun_comm, :string_received],
    [:vws, :sun_comm, :string_rejected],
    [:vws, :sun_comm, :retransmission],
    [:vws, :sun_comm, :reply_sent],
    [:vws, :sun_comm, :rule_broken],
    [:vws, :sun_comm, :wc_connected],
    [:vws, :sun_comm, :wc_disconnected],
    [:vws, :sun_comm, :nc_line],
    [:vws, :partition, :command_dispatched],
    [:vws, :partition, :command, :start],
    [:vws, :partition, :command, :stop],
    [:vws, :partition, :command, :exception],
    [:vws, :partition, :command_finished],
    [:vws, :events, :caused],
    [:vws, :val, :message],
    [:vws, :val, :request_finished],
    [:vws, :val, :async],
    [:vws, :ddcmp, :frame_sent],
    [:vws, :ddcmp, :frame_received],
    [:vws, :ddcmp, :nak],
    [:vws, :ddcmp, :rep],
    [:vws, :ddcmp, :retransmission],
    [:vws, :ddcmp, :receive_error],
    [:vws, :ddcmp, :state_change],
    [:vws, :ddcmp, :link_down],
    [:vws, :ddcmp, :connect_failed],
    [:vws, :dnc, :connected],
    [:vws, :dnc, :disconnected],
    [:vws, :dnc, :connect_failed],
    [:vws, :dnc, :block_sent],
    [:vws, :dnc, :block_received],
    [:vws, :monarch, :request_again],
    [:vws, :dnc, :retry],
    [:vws, :dnc, :transmission],
    [:vws, :dnc, :progress],
    [:vws, :monarch, :program_received],
    [:vws, :hpib, :connected],
    [:vws, :hpib, :disconnected],
    [:vws, :hpib, :timeout],
    [:vws, :hpib, :retry],
    [:vws, :hpib, :connect_failed],
    [:vws, :vws_status, :poll],
    [:vws, :vws_status, :missed],
    [:vws, :vws_status, :stale],
    [:vws, :vws_status, :actuation_retry],
    [:vws, :hydraulic_controller, :relay_corrected],
    [:vws, :partition, :cleaned_up],
    [:vws, :web, :request],
    [:vws, :interlock, :acquired],
    [:vws, :interlock, :refused],
    [:vws, :interlock, :released],
    [:vws, :sim, :plant, :actuator],
    [:vws, :sim, :val2, :command],
    [:vws, :sim, :ge2000, :command],
    [:vws, :sim, :ge2000, :cycle_start],
    [:vws, :sim, :ge2000, :drip_feed]
  ]

  @doc "Every event name listed in the moduledoc."
  @spec events() :: [event_name]
  def events, do: @events

  # Asked once per node: looking for a module that is not there costs a code-path search (~0.6 ms).
  defp telemetry? do
    case :persistent_term.get({__MODULE__, :telemetry_loaded?}, nil) do
      nil ->
        loaded? = Code.ensure_loaded?(:telemetry)
        :persistent_term.put({__MODULE__, :telemetry_loaded?}, loaded?)
        loaded?

      loaded? ->
        loaded?
    end
  end

  @doc "Emits an event (`:telemetry.execute/3`)."
  @spec execute(event_name, map, map) :: :ok
  def execute(event, measurements, metadata \\ %{}) do
    if telemetry?() do
      apply(:telemetry, :execute, [event, measurements, metadata])
    else
      for {id, fun, config} <- :persistent_term.get({__MODULE__, event}, []) do
        try do
          fun.(event, measurements, metadata, config)
        rescue
          e ->
            Logger.error(
              "telemetry handler #{inspect(id)} failed and was detached: " <> Exception.message(e)
            )

            detach(id)
        end
      end

      :ok
    end
  end

  @doc """
  Runs `fun` (which returns `{result, stop_metadata}`) between `prefix ++ [:start]` and
  `prefix ++ [:stop]`, or `prefix ++ [:exception]` if it raises, exits or throws (`:telemetry.span/3`).
  """
  @spec span(event_name, map, (() -> {result, map})) :: result when result: var
  def span(prefix, metadata, fun) do
    if telemetry?() do
      apply(:telemetry, :span, [prefix, metadata, fun])
    else
      start = System.monotonic_time()

      execute(
        prefix ++ [:start],
        %{system_time: System.system_time(), monotonic_time: start},
        metadata
      )

      try do
        {result, stop_metadata} = fun.()
        stop = System.monotonic_time()
        execute(prefix ++ [:stop], %{duration: stop - start, monotonic_time: stop}, stop_metadata)
        result
      catch
        kind, reason ->
          stop = System.monotonic_time()

          execute(
            prefix ++ [:exception],
            %{duration: stop - start, monotonic_time: stop},
            Map.merge(metadata, %{kind: kind, reason: reason, stacktrace: __STACKTRACE__})
          )

          :erlang.raise(kind, reason, __STACKTRACE__)
      end
    end
  end

  @doc "Attaches a handler to one event (`:telemetry.attach/4`)."
  @spec attach(term, event_name, handler_function, term) :: :ok | {:error, :already_exists}
  def attach(id, event, fun, config), do: attach_many(id, [event], fun, config)

  @doc "Attaches a handler to several events (`:telemetry.attach_many/4`)."
  @spec attach_many(term, [event_name], handler_function, term) :: :ok | {:error, :already_exists}
  def attach_many(id, events, fun, config) do
    if telemetry?() do
      apply(:telemetry, :attach_many, [id, events, fun, config])
    else
      :global.trans(
        {__MODULE__, self()},
        fn ->
          if id in :persistent_term.get({__MODULE__, :ids}, []) do
            {:error, :already_exists}
          else
            :persistent_term.put({__MODULE__, :ids}, [
              id | :persistent_term.get({__MODULE__, :ids}, [])
            ])

            for event <- events do
              key = {__MODULE__, event}
              :persistent_term.put(key, :persistent_term.get(key, []) ++ [{id, fun, config}])
            end

            :persistent_term.put({__MODULE__, {:events_of, id}}, events)
            :ok
          end
        end,
        [node()]
      )
    end
  end

  @doc "Detaches a handler (`:telemetry.detach/1`)."
  @spec detach(term) :: :ok | {:error, :not_found}
  def detach(id) do
    if telemetry?() do
      apply(:telemetry, :detach, [id])
    else
      :global.trans(
        {__MODULE__, self()},
        fn ->
          ids = :persistent_term.get({__MODULE__, :ids}, [])

          if id in ids do
            for event <- :persistent_term.get({__MODULE__, {:events_of, id}}, []) do
              key = {__MODULE__, event}

              :persistent_term.put(
                key,
                Enum.reject(:persistent_term.get(key, []), &(elem(&1, 0) == id))
              )
            end

            :persistent_term.erase({__MODULE__, {:events_of, id}})
            :persistent_term.put({__MODULE__, :ids}, List.delete(ids, id))
            :ok
          else
            {:error, :not_found}
          end
        end,
        [node()]
      )
    end
  end

  @doc "Attaches `handle_default_event/4` to every event of `events/0`: each is logged at `level`."
  @spec attach_default_handler(Logger.level()) :: :ok | {:error, :already_exists}
  def attach_default_handler(level \\ :debug) do
    attach_many("vws-default-logger", @events, &__MODULE__.handle_default_event/4, level)
  end

  @doc false
  def handle_default_event(event, measurements, metadata, level) do
    meta = Map.take(metadata, [:workstation, :partition, :command])

    Logger.log(
      level,
      fn ->
        "#{Enum.join(event, ".")} #{inspect(measurements)} #{inspect(Map.drop(metadata, [:stacktrace]))}"
      end,
      Map.to_list(meta)
    )
  end
end
