defmodule Vws.Peers.WC.Runner.Summary do
  @moduledoc """
  What a `Vws.Peers.WC.Runner` run did: whether the script completed, where and why it stopped, and
  the counts of the dialogue.

    * `result` — `:completed` or `:stopped`
    * `stopped` — nil, or `%{step, line, source, reason, error}`: the step that failed, its script
      line and text, the reason in words, and the error term
    * `steps_total`, `steps_done` — steps in the script, steps that succeeded
    * `strings`, `commands`, `status_queries` — strings sent (not counting resends), WC commands
      in them, status queries among them
    * `resends`, `naks`, `timeouts` — strings or lines sent again, `E` answers received, replies
      that did not come in time
    * `program_lines_sent`, `program_lines_received`, `uploads` (the programs received)
    * `transfers_broken` — program transfers that broke off on the link (each made again while
      `:transfer_retries` allowed)
    * `elapsed_ms`
  """

  @enforce_keys [:result, :steps_total, :steps_done]
  defstruct script: nil,
            result: nil,
            stopped: nil,
            steps_total: 0,
            steps_done: 0,
            strings: 0,
            commands: 0,
            status_queries: 0,
            resends: 0,
            naks: 0,
            timeouts: 0,
            program_lines_sent: 0,
            program_lines_received: 0,
            transfers_broken: 0,
            uploads: [],
            elapsed_ms: 0

  @type t :: %__MODULE__{
          script: Path.t() | nil,
          result: :completed | :stopped,
          stopped:
            nil
            | %{
                step: pos_integer,
                line: pos_integer,
                source: String.t(),
                reason: String.t(),
                error: term
              },
          steps_total: non_neg_integer,
          steps_done: non_neg_integer,
          strings: non_neg_integer,
          commands: non_neg_integer,
          status_queries: non_neg_integer,
          resends: non_neg_integer,
          naks: non_neg_integer,
          timeouts: non_neg_integer,
          program_lines_sent: non_neg_integer,
          program_lines_received: non_neg_integer,
          transfers_broken: non_neg_integer,
          uploads: [[String.t()]],
          elapsed_ms: non_neg_integer
        }

  @doc "Whether the script ran to its end."
  @spec completed?(t) :: boolean
  def completed?(%__MODULE__{result: result}), do: result == :completed

  @doc """
  The summary as printable lines. The `result:` line is `COMPLETED` or `STOPPED at line N (step
  i of n): reason`.

      iex> Vws.Peers.WC.Runner.Summary.format(%Vws.Peers.WC.Runner.Summary{result: :completed, steps_total: 2, steps_done: 2})
      ...> |> Enum.take(2)
      ["== Summary ==", "result:          COMPLETED"]
  """
  @spec format(t) :: [String.t()]
  def format(%__MODULE__{} = s) do
    ["== Summary ==", "result:          " <> result(s)] ++
      if(s.script, do: ["script:          #{s.script}"], else: []) ++
      [
        "steps done:      #{s.steps_done} of #{s.steps_total}",
        "WC commands:     #{s.commands}",
        "strings sent:    #{s.strings} (#{s.status_queries} #{if s.status_queries == 1, do: "status query", else: "status queries"})",
        "resends:         #{s.resends} (E received: #{s.naks}, no reply in time: #{s.timeouts})",
        "program lines:   #{s.program_lines_sent} sent, #{s.program_lines_received} received" <>
          if(s.transfers_broken > 0,
            do: " (#{s.transfers_broken} transfers broke off and were made again)",
            else: ""
          ),
        "elapsed:         #{:erlang.float_to_binary(s.elapsed_ms / 1000, decimals: 2)} s"
      ]
  end

  defp result(%{result: :completed}), do: "COMPLETED"

  defp result(%{stopped: st, steps_total: total}),
    do: "STOPPED at line #{st.line} (step #{st.step} of #{total}): #{st.reason}"
end
