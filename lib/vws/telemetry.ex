defmodule Vws.Telemetry do
  # THE catalogue: every event the code emits, with its measurements and metadata. The
  # moduledoc's table is made from it, `events/0` and `attach_default_handler/0` read it, and
  # test/vws/telemetry_catalogue_test.exs fails on an event emitted in lib/ that is not here.
  # Each entry: {event, measurements, metadata, what it means}; a metadata key in brackets
  # (`{:optional, key}`) is there only sometimes.
  @catalogue [
    {[:vws, :sun_comm, :string_received], [:bytes], [:workstation, :sequence, :commands],
     "an intact command string from the WC"},
    {[:vws, :sun_comm, :string_rejected], [:bytes], [:workstation, :reason],
     "a line answered `E` (bad BCC, malformed, empty, too long, unfinished, journal down …)"},
    {[:vws, :sun_comm, :retransmission], [:count], [:workstation, :sequence],
     "a string received again (rule 4): acknowledged again, nothing run"},
    {[:vws, :sun_comm, :reply_sent], [:bytes], [:workstation, :kind],
     "an answer to the WC (`kind`: `:ack`, `:nak`, `:status`, `:line`, `:line_ack`)"},
    {[:vws, :sun_comm, :rule_broken], [:count], [:workstation, :sequence, :rule],
     "an intact string that breaks a Parser rule: nothing in it runs"},
    {[:vws, :sun_comm, :wc_connected], [:count], [:workstation, :peer],
     "a WC connection (or tty) became the link"},
    {[:vws, :sun_comm, :wc_disconnected], [:count], [:workstation, :peer, :reason],
     "the WC link ended (`reason`: `:taken_over` or why it was lost)"},
    {[:vws, :sun_comm, :wc_refused], [:count], [:workstation, :peer, :current],
     "a new WC connection refused while the current WC (`current`) is not silent"},
    {[:vws, :sun_comm, :nc_line], [:bytes], [:workstation, :direction],
     "an NC program line stored (`:in`, DOWNLOAD_HP) or sent (`:out`, UPLOAD_SUN)"},
    {[:vws, :transport, :refused], [:count], [:peer, :listener],
     "a connection the listener's allow-list does not let in (`Vws.Links.Transport.Policy`)"},
    {[:vws, :partition, :command_dispatched], [:count],
     [:workstation, :partition, :command, :text],
     "a command written to CMD_IN (`Vws.CEC.Partition.dispatch/4`; SUN_COMM's transfers)"},
    {[:vws, :partition, :command, :start], [:system_time, :monotonic_time],
     [:workstation, :partition, :command, :text], "a partition starts a command (span)"},
    {[:vws, :partition, :command, :stop], [:duration, :monotonic_time],
     [:workstation, :partition, :command, :text, :result], "the command ended (span)"},
    {[:vws, :partition, :command, :exception], [:duration, :monotonic_time],
     [:workstation, :partition, :command, :text, :kind, :reason, :stacktrace],
     "the command raised (span)"},
    {[:vws, :partition, :command_finished], [:duration],
     [:workstation, :partition, :command, :status],
     "a command status set DONE or ERROR (`duration` native; 0 for SUN_COMM's transfers)"},
    {[:vws, :partition, :cleaned_up], [:count],
     [:workstation, :partition, :command, :text, :status],
     "the safe clean-up of a command a restart interrupted"},
    {[:vws, :events, :caused], [:count], [:workstation, :event],
     "CAUSE EVENT (`Vws.CEC.Events`)"},
    {[:vws, :val, :message], [:bytes],
     [:name, :workstation, :direction, :lun, :function, :qualifier, :text],
     "a VAL II logical-unit message"},
    {[:vws, :val, :request_finished], [:duration], [:name, :workstation, :text, :result],
     "a VAL II request answered or failed (`duration` native)"},
    {[:vws, :val, :async], [:count], [:name, :workstation, :code, :text], "every LUN 3 message"},
    {[:vws, :ddcmp, :frame_sent], [:count],
     [:link, :workstation, :type, :num, :resp, :bytes, :subtype, :rcvr, :sndr],
     "a DDCMP frame sent, with the frame's fields"},
    {[:vws, :ddcmp, :frame_received], [:count],
     [:link, :workstation, :type, :num, :resp, :bytes, :subtype, :rcvr, :sndr],
     "a DDCMP frame received, with the frame's fields"},
    {[:vws, :ddcmp, :nak], [:count], [:link, :workstation, :direction, :reason, :resp],
     "a NAK sent or received"},
    {[:vws, :ddcmp, :rep], [:count], [:link, :workstation, :direction, :num],
     "a REP sent or received"},
    {[:vws, :ddcmp, :retransmission], [:count, :bytes], [:link, :workstation, :num],
     "a data message sent again"},
    {[:vws, :ddcmp, :receive_error], [:count], [:link, :workstation, :reason, :num],
     "a damaged frame received"},
    {[:vws, :ddcmp, :state_change], [:count], [:link, :workstation, :from, :to],
     "the link's state changed"},
    {[:vws, :ddcmp, :link_down], [:count], [:link, :workstation, :reason], "the link went down"},
    {[:vws, :ddcmp, :connect_failed], [:count, :retry_in],
     [:link, :workstation, :endpoint, :reason],
     "the transport could not be opened (`retry_in` ms)"},
    {[:vws, :dnc, :connected], [:count], [:link, :workstation, :role, :peer],
     "the GE-2000 DNC link connected"},
    {[:vws, :dnc, :disconnected], [:count], [:link, :workstation, :role, :peer, :reason],
     "the DNC link disconnected"},
    {[:vws, :dnc, :connect_failed], [:count, :retry_in],
     [:link, :workstation, :role, :endpoint, :reason],
     "the DNC transport could not be opened (`retry_in` ms)"},
    {[:vws, :rfc2217, :line_state], [:count], [:endpoint, :errors],
     "an RFC 2217 terminal server reports line errors (overrun, parity, framing, break)"},
    {[:vws, :rs232, :connected], [:count], [:link, :workstation, :peer],
     "a plain RS-232 DNC port (`Vws.Links.RS232`) connected"},
    {[:vws, :rs232, :disconnected], [:count], [:link, :workstation, :peer, :reason],
     "the RS-232 DNC port disconnected"},
    {[:vws, :rs232, :connect_failed], [:count, :retry_in],
     [:link, :workstation, :endpoint, :reason],
     "the RS-232 DNC port's transport could not be opened (`retry_in` ms)"},
    {[:vws, :rs232, :transfer], [:bytes, :duration], [:link, :direction, :operation, :result],
     "a program sent (`:out`, with its read-back) or received (`:in`) on an RS-232 port (ms)"},
    {[:vws, :rs232, :xoff], [:count], [:link],
     "an XOFF (DC3) from the control: the RS-232 port stops sending until DC1"},
    {[:vws, :dnc, :block_sent], [:bytes], [:link, :workstation, :role, :block, :retransmission],
     "a DNC block sent"},
    {[:vws, :dnc, :block_received], [:bytes], [:link, :workstation, :role, :block],
     "a DNC block received"},
    {[:vws, :dnc, :retry], [:count], [:link, :workstation, :role, :kind, :block],
     "a DNC block or bid tried again"},
    {[:vws, :dnc, :pause], [:count], [:link, :workstation, :role, :kind, :block],
     "the DNC receiver asked the sender to wait (WACK: flow control, not a fault)"},
    {[:vws, :dnc, :transmission], [:duration, :blocks, :bytes],
     [:link, :workstation, :role, :direction, :kind, :result],
     "a whole DNC transmission ended (`kind` on `:out`)"},
    {[:vws, :dnc, :progress], [:blocks, :bytes, :program_bytes, :chars_per_s, :retries, :pauses],
     [
       :link,
       :workstation,
       :role,
       :program,
       :operation,
       :direction,
       :total_blocks,
       :total_bytes,
       :total_program_bytes,
       :eta_s,
       :ended
     ],
     "an NC program's transfer: after every block, and once at its end (`ended`: `:ok` or why)"},
    {[:vws, :monarch, :request_again], [:count], [:workstation, :operation, :reason],
     "MONARCH made a DNC request again after the line broke it off"},
    {[:vws, :web, :request], [:duration, :bytes], [:method, :path, :status, :port],
     "an HTTP request answered (dashboard, MTConnect agent)"},
    {[:vws, :hpib, :connected], [:count], [:bus, :address, :endpoint],
     "an HPIB device connected"},
    {[:vws, :hpib, :disconnected], [:count], [:bus, :address, :endpoint, :reason],
     "an HPIB device disconnected"},
    {[:vws, :hpib, :timeout], [:count], [:bus, :address, :endpoint, :commands],
     "an HPIB request not answered in time"},
    {[:vws, :hpib, :retry], [:count], [:bus, :address, :endpoint, :commands, :reason, :try],
     "an HPIB request made again"},
    {[:vws, :hpib, :connect_failed], [:count, :retry_in], [:bus, :address, :endpoint, :reason],
     "an HPIB device could not be reached (`retry_in` ms)"},
    {[:vws, :vws_status, :poll], [:started_at, :lateness, :duration, :handling],
     [:workstation, :seq, :result],
     "a poll of DAQ #1 (µs: `started_at` monotonic, `lateness` after its time, `duration` until answered, `handling` in VWS_STATUS)"},
    {[:vws, :vws_status, :missed], [:count], [:workstation, :reason],
     "poll times skipped (`:busy` or `:held_up`)"},
    {[:vws, :vws_status, :stale], [:count], [:workstation, :reason],
     "the readings went stale: NO DATA written"},
    {[:vws, :vws_status, :actuation_retry], [:count], [:workstation, :reason, :try],
     "relays set again after a read-back not as commanded"},
    {[:vws, :vws_status, :shedding], [:stretch], [:pool, :due, :late, :missed],
     "the polls of a pool stretched or relaxed: each polls every `stretch` periods (load shedding)"},
    {[:vws, :hydraulic_controller, :relay_corrected], [:count], [:device],
     "a DAQ #2 slot read back not as intended, set right"},
    {[:vws, :interlock, :acquired], [:wait_ms, :tries], [:workstation, :volume, :holder, :reason],
     "a work-volume lease taken"},
    {[:vws, :interlock, :refused], [:wait_ms, :tries],
     [:workstation, :volume, :holder, :reason, :why], "a lease refused at its time limit"},
    {[:vws, :interlock, :released], [:count], [:workstation, :volume, :holder, :reason],
     "a reason of a lease given up (`reason`: `:all` or one)"},
    {[:vws, :sim, :plant, :actuator], [:count], [:workstation, :daq, :channel, :signal, :action],
     "every relay a simulated DAQ wrote (`action`: `:close`/`:open`)"},
    {[:vws, :sim, :val2, :command], [:count], [:workstation, :text],
     "every monitor command the simulated VAL II obeyed"},
    {[:vws, :monarch, :program_received], [:bytes], [:workstation, :program, :from, :result],
     "a program the operator sent from the machine (`from: :machine`), kept or refused"},
    {[:vws, :monarch, :remote_request], [:bytes],
     [:workstation, :program, :version, :result, :reason, :verified],
     "a program the operator asked for from the machine's panel (`RCS`): sent and verified, or refused"},
    {[:vws, :monarch, :drip_restart], [:line], [:workstation, :program, :version, :preamble],
     "a drip feed restarted at a line: the modal state restored before its first block"},
    {[:vws, :sim, :ge2000, :command], [:bytes], [:workstation, :operation, :name, :alarm],
     "every S command the simulated GE-2000 took"},
    {[:vws, :sim, :ge2000, :cycle_start], [:count], [:workstation, :program],
     "every cycle the simulated GE-2000 started"},
    {[:vws, :sim, :ge2000, :drip_feed], [:bytes], [:workstation, :program, :result, :underruns],
     "a drip feed the simulated GE-2000 ran to its end"}
  ]

  @table Enum.map_join(@catalogue, "\n", fn {event, measurements, metadata, what} ->
           keys = &Enum.map_join(&1, ", ", fn k -> "`#{k}`" end)
           "| `#{inspect(event)}` | #{keys.(measurements)} | #{keys.(metadata)} | #{what} |"
         end)

  @moduledoc """
  The one seam between VWS and telemetry, with the contract of the `:telemetry` library
  (`execute/3`, `span/3`, `attach/4`, `attach_many/4`, `detach/1`), and the catalogue of every
  event VWS emits.

  When `:telemetry` is loaded (a deployment that has the hex package), every call is delegated to
  it. Otherwise handlers are kept here, in `:persistent_term` (attaching is rare, emitting is
  frequent), and called synchronously in the emitting process exactly as `:telemetry` would; a
  handler that raises is detached and logged, as `:telemetry` does.

  ## Events

  Names are `[:vws, component, happening]` for points and `[:vws, component, thing, :start |
  :stop | :exception]` for spans: `:start` measures `system_time, monotonic_time`, `:stop` and
  `:exception` `duration, monotonic_time` (native units), `:exception` adds `kind, reason,
  stacktrace` to the metadata. This table is the whole list (`catalogue/0`); a test fails on an
  event emitted in `lib/` that it does not name, and on measurements other than these.

  | event | measurements | metadata | what |
  |-------|--------------|----------|------|
  #{@table}

  `workstation` is the id of the workstation the event belongs to (nil for a link or simulator
  that serves none). The `[:vws, :sim, …]` events come from the simulators: what the simulated
  equipment physically did, for tests that count executions. `attach_default_handler/0` logs
  all of them with `Logger`.
  """

  require Logger

  @type event_name :: [atom, ...]
  @type handler_function :: (event_name, map, map, term -> any)
  @type entry :: %{
          event: event_name,
          measurements: [atom],
          metadata: [atom],
          description: String.t()
        }

  @events Enum.map(@catalogue, &elem(&1, 0))

  @doc "Every event name of the catalogue."
  @spec events() :: [event_name]
  def events, do: @events

  @doc "The catalogue: every event with its measurements, metadata and meaning."
  @spec catalogue() :: [entry]
  def catalogue do
    for {event, measurements, metadata, what} <- @catalogue,
        do: %{event: event, measurements: measurements, metadata: metadata, description: what}
  end

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

  @doc """
  Whether any handler is attached to `event`: for an event emitted so often (a poll every 20 ms
  per workstation) that building its measurements for nobody is worth a look first.
  """
  @spec listened?(event_name) :: boolean
  def listened?(event) do
    if telemetry?(),
      do: apply(:telemetry, :list_handlers, [event]) |> Enum.any?(&(&1.event_name == event)),
      else: :persistent_term.get({__MODULE__, event}, []) != []
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
