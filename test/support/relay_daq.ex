defmodule Vws.Test.RelayDAQ do
  @moduledoc """
  A workstation whose VWS_STATUS drives a simulated DAQ #1 alone, for the tests of relay
  writes: a plant at time scale 0, its DAQ, optionally a `Vws.Test.FlipRelay` on the line, and
  no polls (the traffic is the actuations' alone, and no start-up release of the button comes
  in between). Call from a test or its setup (it starts supervised processes).
  """

  import ExUnit.Callbacks, only: [start_supervised!: 1, on_exit: 1]
  import Vws.Test.Eventually

  alias Vws.Partitions.VwsStatus
  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Test.{FlipRelay, Workstation}

  @doc """
  Starts it: `%{ws, plant, daq, relay}` (`relay` nil without one). Options: `:timeout_ms` of
  VWS_STATUS (default 150), `:flip_relay` (default true).
  """
  def start(opts \\ []) do
    plant = start_supervised!({Plant, time_scale: 0})
    daq = start_supervised!({DAQ, plant: plant})

    relay =
      if Keyword.get(opts, :flip_relay, true) do
        {:ok, relay} = FlipRelay.start_link(DAQ.endpoint(daq))
        relay
      end

    endpoint = if relay, do: FlipRelay.endpoint(relay), else: DAQ.endpoint(daq)
    vws_status = [poll_ms: 600_000, timeout_ms: Keyword.get(opts, :timeout_ms, 150)]
    %{ws: ws} = Workstation.start(devices: [daq1: [endpoint: endpoint, vws_status: vws_status]])

    unless eventually(fn -> VwsStatus.actuate(ws, []) == :ok and connected?(ws) end),
      do: raise("VWS_STATUS of #{ws} did not come up")

    %{ws: ws, plant: plant, daq: daq, relay: relay}
  end

  defp connected?(ws), do: VwsStatus.stats(ws)[:link] != nil

  @doc """
  Sends the caller `{:actuation_retry, reason, try}` for every retry of `ws`'s actuations (the
  other tests' workstations retry too), after `also.(metadata)` if given; detached when the
  test ends.
  """
  def forward_retries(ws, also \\ fn _metadata -> :ok end) do
    handler = "actuation-retry-#{inspect(ws)}-#{System.unique_integer([:positive])}"
    test_pid = self()

    :ok =
      Vws.Telemetry.attach(
        handler,
        [:vws, :vws_status, :actuation_retry],
        fn _, _, md, _ ->
          if md.workstation == ws do
            also.(md)
            send(test_pid, {:actuation_retry, md.reason, md.try})
          end
        end,
        nil
      )

    on_exit(fn -> Vws.Telemetry.detach(handler) end)
  end
end
