defmodule Vws.Peers.HydraulicController do
  @moduledoc """
  The hydraulic controller (seed §5; PROTOCOLS.md §4): the HP-9836 program that clamps the pallet
  to the machine table. It is a device on the CEC's HPIB and the controller of its own HPIB, on
  which DAQ #2 drives the pallet's valves and reads its microswitches and clamp-force gauges.

  It is a self-contained supervision tree, the same in the workstation's node or in a node of
  its own — it shares nothing with the CEC but the HPIB link — started with `start_link/1` or,
  as a program of its own, with `mix vws.hydraulic`:

      Vws.Peers.HydraulicController.start_link(listen: "tcp://0.0.0.0:5026", daq2: "tcp://10.0.0.10:5025")

  ```
  Vws.Peers.HydraulicController (rest_for_one)
  ├── CecPort    holds the CEC's endpoint (`:listen`), the same across program restarts
  ├── Vws.Links.HPIB   DAQ #2 at address 9 on the controller's own bus {:hydraulic_controller, name}
  └── Program    the 3 initialisation routines, the command status, the sequences (workers)
      ├── acceptor                     CEC connections, from the end of initialisation on
      └── Options (one per connection) reads, parses and carries out each command line
  ```

  ## The program (seed §5.1)

  On start-up it runs its three initialisation routines in order: (1) the HPIB link with the
  CEC — it listens on `:listen`; (2) the HPIB link with DAQ #2 — it waits for its `Vws.Links.HPIB`
  device to connect and identifies the instrument (`*IDN?`); (3) depressurise — every valve relay
  opened and both clamp forces confirmed near zero, so the swing clamps are fully released
  (`Vws.Peers.HydraulicController.Pallet.depressurise/1`). Only then does it accept the CEC. If DAQ #2
  could not be reached or the clamps not confirmed released, it serves the CEC all the same —
  `STATUS?` says `ERROR NOT DEPRESSURISED AT START-UP: <why>` — and CLAMP_PALLET depressurises
  first. A restart of the program depressurises again, as switching the HP-9836 on did.

  Then the task manager `Options` serves each CEC connection, line by line (SCPI, `Vws.Codecs.SCPI`):

  | line | what happens | answer |
  |------|--------------|--------|
  | `CLAMP_PALLET` | rams X then Y, then clamps 1 and 2, each confirmed on DAQ #2 | none |
  | `RELEASE_PALLET` | the same in reverse | none |
  | `STATUS?` | — (answered at once, also while a sequence runs) | `DONE`, `EXECUTING`, `ERROR <reason>` |
  | `PALLET?` | DAQ #2 read now | `PALLET CLAMPED X=1 Y=1 F1=… F2=…` / `PALLET NOT CLAMPED …` |
  | `*IDN?` | — | `NBS-VWS,HP-9836 HYDRAULIC CONTROLLER,0,1.0` |

  The status is that of the last command: `EXECUTING` while its sequence runs, then `DONE` or
  `ERROR` with what was measured (`ERROR CLAMP 2 FORCE 1200 N BELOW 4000 N`, `ERROR PALLET NOT
  AGAINST X STOP`, `ERROR DAQ #2 NOT ANSWERING (NO ANSWER IN 500 MS)`; see
  `Vws.Peers.HydraulicController.Pallet`). A command that comes while a sequence runs is not run and
  changes nothing (the CEC sends one at a time: it waits for a status other than EXECUTING).
  When DAQ #2 cannot be read, `PALLET?` answers `PALLET NOT CLAMPED X=0 Y=0` with both forces
  at the overload value 9.9E+37 — nothing confirmed.

      iex> {:ok, plant} = Vws.Sim.Plant.start_link(time_scale: 1000)
      iex> {:ok, daq2} = Vws.Sim.DAQ.start_link(plant: plant, daq: :daq2)
      iex> {:ok, _} = Vws.Peers.HydraulicController.start_link(name: "doc", daq2: Vws.Sim.DAQ.endpoint(daq2))
      iex> Vws.Peers.HydraulicController.await_ready("doc", 5_000)
      :ok
      iex> Vws.Peers.HydraulicController.status("doc")
      :done
      iex> Vws.Peers.HydraulicController.endpoint("doc") =~ ~r"^tcp://127.0.0.1:\\d+$"
      true
  """
  use Supervisor

  alias Vws.Peers.HydraulicController.{CecPort, Pallet, Program}

  @daq2_address 9

  @doc false
  def child_spec(opts) do
    %{
      id: {__MODULE__, Keyword.get(opts, :name, :hydraulic_controller)},
      start: {__MODULE__, :start_link, [opts]},
      type: :supervisor
    }
  end

  @doc """
  Starts the controller. Options:

    * `:daq2` — the endpoint of DAQ #2 (required);
    * `:listen` — where the CEC reaches it (default `"tcp://127.0.0.1:0"`, a free port: see
      `endpoint/1`);
    * `:allow` — the CEC's address (or an allow-list, `Vws.Links.Transport.Policy`): only it may
      connect and send commands (default loopback only). Listening on an address that is not
      loopback without it is refused: a raw `CLAMP_PALLET` from anyone else would bypass the
      CEC and its interlocks;
    * `:name` — any term naming this controller in `Vws.Registry` (default
      `:hydraulic_controller`); it names the DAQ #2 bus `{:hydraulic_controller, name}` too;
    * `:daq2_address` — DAQ #2's primary address on that bus (default #{@daq2_address});
    * `:hpib` — more `Vws.Links.HPIB.start_link/1` options for DAQ #2 (`:backoff`, `:connect_timeout`);
    * `:connect_timeout_ms` — how long init routine 2 waits for DAQ #2 (default 2000);
    * `:min_force_n`, `:released_n`, `:step_timeout_ms`, `:poll_ms`, `:timeout_ms`,
      `:channel_map` — the pallet's (`Vws.Peers.HydraulicController.Pallet.new/2`).
  """
  @spec start_link(keyword) :: Supervisor.on_start()
  def start_link(opts) do
    Keyword.fetch!(opts, :daq2)
    name = Keyword.get(opts, :name, :hydraulic_controller)
    Supervisor.start_link(__MODULE__, Keyword.put(opts, :name, name), name: via(name, :sup))
  end

  @doc "Where the CEC reaches the controller (with the real port when port 0 was asked)."
  @spec endpoint(term) :: String.t()
  def endpoint(name \\ :hydraulic_controller), do: GenServer.call(via(name, :program), :endpoint)

  @doc "The command status, as `STATUS?` answers it."
  @spec status(term) :: :done | :executing | {:error, String.t()}
  def status(name \\ :hydraulic_controller), do: GenServer.call(via(name, :program), :status)

  @doc """
  Waits until the initialisation routines are over and CEC connections are accepted: `:ok`, or
  `:timeout`.
  """
  @spec await_ready(term, timeout) :: :ok | :timeout
  def await_ready(name \\ :hydraulic_controller, timeout) do
    GenServer.call(via(name, :program), :await_ready, timeout)
  catch
    :exit, {:timeout, _} -> :timeout
  end

  @doc """
  What the program is doing: `%{phase (:initialising | :ready), status, depressurised, running,
  init_result, endpoint, connections, open_connections, commands, sequences, refused_busy}`.
  """
  @spec info(term) :: map
  def info(name \\ :hydraulic_controller), do: GenServer.call(via(name, :program), :info)

  @doc "The DAQ #2 HPIB device of a controller, `{bus, address}` (for `Vws.Links.HPIB.info/1`)."
  @spec daq2_device(term, keyword) :: Vws.Links.HPIB.device()
  def daq2_device(name \\ :hydraulic_controller, opts \\ []),
    do: {{:hydraulic_controller, name}, Keyword.get(opts, :daq2_address, @daq2_address)}

  @impl true
  def init(opts) do
    name = Keyword.fetch!(opts, :name)
    {bus, address} = device = daq2_device(name, opts)

    hpib =
      [bus: bus, address: address, endpoint: Keyword.fetch!(opts, :daq2), device: "DAQ #2"] ++
        Keyword.get(opts, :hpib, [])

    pallet =
      Pallet.new(
        device,
        Keyword.take(opts, [
          :min_force_n,
          :released_n,
          :step_timeout_ms,
          :poll_ms,
          :timeout_ms,
          :channel_map
        ])
      )

    allow = Vws.Links.Transport.Policy.parse_allow!(Keyword.get(opts, :allow))

    cec_port = [
      registered_as: via(name, :cec_port),
      listen: Keyword.get(opts, :listen, "tcp://127.0.0.1:0"),
      allow: allow
    ]

    program = [
      name: name,
      registered_as: via(name, :program),
      cec_port: via(name, :cec_port),
      allow: allow,
      pallet: pallet,
      connect_timeout_ms: Keyword.get(opts, :connect_timeout_ms, 2_000)
    ]

    children = [
      %{id: CecPort, start: {CecPort, :start_link, [cec_port]}},
      {Vws.Links.HPIB, hpib},
      %{id: Program, start: {Program, :start_link, [program]}}
    ]

    Supervisor.init(children, strategy: :rest_for_one)
  end

  defp via(name, role),
    do: Vws.Names.via({:hydraulic_controller, name}, role)
end
