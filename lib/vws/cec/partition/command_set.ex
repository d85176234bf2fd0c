defmodule Vws.CEC.Partition.CommandSet do
  @moduledoc """
  What a command partition's module implements: its set's grammar and what running a command
  means (ROBOT, MONARCH, GRIPPER, FIXTURE, VACUUM, HYDRAULIC; `Vws.Partitions.*`).

  `Vws.CEC.Partition` runs the seed's partition loop around it (§2.3, Fig. 4); this module holds
  only the callbacks and their types, and depends on nothing, so a command set compiles against
  it without recompiling when the loop, the mailboxes or the interlocks change.

      defmodule MyPartition do
        @behaviour Vws.CEC.Partition.CommandSet

        @impl true
        def device, do: "DAQ #1"
        @impl true
        def parse("OPEN"), do: {:ok, :open}
        def parse(_), do: {:error, :unknown}
        @impl true
        def execute(:open, _ctx), do: :done
      end

  `parse/1` gives `{:error, :unknown}` for text outside the set (answered `ERROR UNKNOWN COMMAND
  <text>`) or `{:error, words}` for a command of the set that is wrong. `execute/2` runs in a
  process of its own, linked to the partition; it returns `:done` or `{:error, words}`, words
  and numbers the WC can read.

  ## Interlocks

  Between the grammar and `execute/2`, every command passes the one interlock table
  (`Vws.CEC.Interlock.Rules`). A module takes part through three optional callbacks:
  `volumes/2`, the work volumes a command's target lies in (ROBOT's motions); `conditions/2`,
  the physical conditions of a volume (the machine idle and the table parked); and
  `missing_link/2`, a second device a command needs beyond the partition's link (MONARCH's
  CYCLE_START: the relay on DAQ #1), refused `ERROR NO LINK TO <device>` before anything is
  taken.

  ## After a restart of the workstation

  `interrupted/2`, optional, is the safe clean-up of a command the restart interrupted: the state
  a failed command of the set leaves the device in, never the command's work (the vise: both
  valves off, so the jaws hold where they are).
  """

  @typedoc """
  What a command runs with: its workstation, partition, number and text, whatever the module
  needs to reach its device (`link`, `nil` when not configured) and the partition's `options`.
  """
  @type ctx :: %{
          required(:workstation) => term,
          required(:partition) => atom,
          required(:number) => 0..9999,
          required(:text) => String.t() | nil,
          required(:link) => term,
          required(:options) => keyword,
          optional(:interlocks) => :on | :off
        }

  @typedoc "A work volume of the interlock table (`Vws.CEC.Interlock`)."
  @type volume :: atom

  @doc "The device the set drives, in the WC's words: \"VAL II\", \"GE-2000\", \"DAQ #1\" …"
  @callback device() :: String.t()

  @doc "The command the text stands for, or why it is not one of the set."
  @callback parse(String.t()) :: {:ok, command :: term} | {:error, :unknown | String.t()}

  @doc "Runs one command on the device: `:done`, or `{:error, words}`."
  @callback execute(command :: term, ctx) :: :done | {:error, String.t()}

  @doc """
  Restores the safe state a command the restart interrupted leaves its device in; `command` is
  `:unknown` when the partition's status was lost with a damaged journal (a command may have been
  under way).
  """
  @callback interrupted(command :: term, ctx) :: :ok | {:error, String.t()}

  @doc "The work volumes the command enters, taken before it runs."
  @callback volumes(command :: term, ctx) :: {:ok, [volume]} | {:error, String.t()}

  @doc "A check of a volume's physical conditions, run when the volume is taken."
  @callback conditions(volume, ctx) :: (() -> :ok | {:error, String.t()})

  @doc "A device the command needs beyond the partition's link and has none to, or nil."
  @callback missing_link(command :: term, ctx) :: String.t() | nil

  @optional_callbacks interrupted: 2, volumes: 2, conditions: 2, missing_link: 2
end
