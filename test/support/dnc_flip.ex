defmodule Vws.Test.DNCFlip do
  @moduledoc """
  The floor and the checks of `Vws.Reliability.DNCBitFlipTest`'s modules: DOWNLOAD_GE and
  UPLOAD_GE under bit errors on the DNC link (issue 15, PROTOCOLS.md §2 "A program is whole or
  it is nothing", "Directory"): for every single-bit flip in every byte of a
  transfer's traffic, both directions — and random bursts — the program arrives unchanged or the
  Monarch command ends `ERROR` with a reason; never `DONE` with other bytes. MONARCH's DNC link
  talks to the simulated GE-2000 over TCP through `Vws.Test.FlipRelay`.

  Before, an ENQ damaged into EOT ended a download early: the GE-2000 kept part of the program
  and MONARCH said DONE.
  """
  import ExUnit.Assertions
  import ExUnit.Callbacks, only: [start_supervised!: 1]

  @doc "An async case whose tests run on the floor of `setup_link/0` (`ctx`), PropEr at hand."
  defmacro __using__(_) do
    quote do
      use ExUnit.Case, async: true
      use Vws.PropCase
      alias Vws.Test.DNCFlip
      @moduletag timeout: 900_000
      setup do: DNCFlip.setup_link()
    end
  end

  alias Vws.Links.DNC
  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.Links.DNC.Program
  alias Vws.Sim.GE2000
  alias Vws.Test.FlipRelay
  alias Vws.Peers.WC.Client
  import Vws.Test.Eventually

  @link_opts [
    reply_timeout: 40,
    response_timeout: 200,
    receive_timeout: 200,
    wack_delay: 10,
    backoff_min: 5,
    backoff_max: 20
  ]
  @program ["%", "O000012", "N10 G1X1", "%"]
  @file_name "000012.PRO"
  @old "%\nO000012\nN10 G0X9\n%\n"
  # drip feed: a program of several text blocks (max_text 64 on both ends)
  @drip ["%", "O000012"] ++ for(i <- 1..12, do: "N#{i * 10} G1X#{i}.5Y-#{i}") ++ ["M30", "%"]

  @doc "The simulated GE-2000 behind a FlipRelay, and a workstation whose MONARCH reaches it."
  def setup_link do
    sim =
      start_supervised!(
        {GE2000, link: [max_text: 64] ++ @link_opts, memory: 4_096, feed_rate: 100_000, tick: 5}
      )

    {:ok, relay} = FlipRelay.start_link(GE2000.endpoint(sim))

    %{ws: ws, wc: wc} =
      Vws.Test.Workstation.start(
        # no status monitor: the DNC traffic is the commands' alone
        devices: [
          ge2000:
            [endpoint: FlipRelay.endpoint(relay), status_interval: nil, max_text: 64] ++
              @link_opts
        ],
        partitions: [monarch: [options: [request_timeout: 20_000]]]
      )

    link = Workstation.whereis(ws, :ge2000)
    assert eventually(fn -> DNC.info(link).state == :idle end)
    {:ok, client} = Client.connect(wc, numbers: %{"M" => 1})
    %{ws: ws, sim: sim, relay: relay, client: client, link: link}
  end

  @doc "The traffic of one clean transfer: {bytes to the GE-2000, bytes back}."
  def traffic(ctx, kind, tries \\ 5) do
    :ok = FlipRelay.plan(ctx.relay, {:bytes, []})

    # the link's timeouts are the test's short ones (40 ms for a reply): on a loaded host a clean
    # line may still end ERROR, which is a right outcome but gives no count of the traffic
    case check!(ctx, kind, []) do
      :done -> :ok
      :error when tries > 1 -> traffic(ctx, kind, tries - 1)
      other -> flunk("a clean #{kind} ended #{inspect(other)} on its last try")
    end

    counts = FlipRelay.counts(ctx.relay)
    assert counts.to_target > 20 and counts.to_client > 20
    {counts.to_target, counts.to_client}
  end

  @doc false
  # One DOWNLOAD_GE or UPLOAD_GE with `flips` on the DNC line: `:done` with the program exactly
  # where it went, or `:error` with a reason; anything else fails the test.
  def check!(ctx, kind, flips) do
    ws = ctx.ws
    text = Program.to_text(@program)
    await_idle(ctx.link)

    case kind do
      :download ->
        :ok = GE2000.put_program(ctx.sim, @file_name, @old)
        :ok = Mailbox.put_nc_file(ws, @program)

      :upload ->
        :ok = GE2000.put_program(ctx.sim, @file_name, text)
        :ok = Mailbox.put_nc_up(ws, [])

      :drip_feed ->
        :ok = Mailbox.put_nc_file(ws, @drip)
    end

    drips = GE2000.state(ctx.sim).drips

    :ok = FlipRelay.plan(ctx.relay, {:bytes, flips})

    command =
      case kind do
        :download -> "DOWNLOAD_GE"
        :upload -> "UPLOAD_GE(#{@file_name})"
        :drip_feed -> "DRIP_FEED"
      end

    {:ok, [{"M", n}]} = Client.send_commands(ctx.client, [{"M", command}])
    result = Client.await_command(ctx.client, "M", n, 120_000, poll_interval: 5)

    case {kind, result} do
      {:download, :done} ->
        assert GE2000.program(ctx.sim, @file_name) == text,
               "DONE with other bytes, flips #{inspect(flips)}"

        :done

      {:upload, :done} ->
        assert Mailbox.nc_up(ws) == @program, "DONE with other bytes, flips #{inspect(flips)}"
        :done

      {:drip_feed, result} ->
        drip_outcome(ctx, result, drips, flips)

      {kind, {:error, %{reason: :command_failed, data: %{status: "ERROR " <> reason}}}}
      when reason != "" ->
        # whole or nothing: NC_UP is never part of a program
        if kind == :upload, do: assert(Mailbox.nc_up(ws) == [])
        :error

      other ->
        flunk("#{inspect(other)}, flips #{inspect(flips)}")
    end
  end

  defp drip_outcome(ctx, result, drips, flips) do
    text = Program.to_text(@drip)

    drip =
      if GE2000.state(ctx.sim).drips > drips do
        assert eventually(fn -> GE2000.drip(ctx.sim).state in [:done, :broken] end, 10_000)
        GE2000.drip(ctx.sim)
      end

    case result do
      :done ->
        assert drip.state == :done and drip.received == byte_size(text) and
                 drip.crc == Vws.Codecs.CRC16.compute(text),
               "DONE with other bytes run, flips #{inspect(flips)}: #{inspect(drip)}"

        :done

      {:error, %{reason: :command_failed, data: %{status: "ERROR " <> reason}}}
      when reason != "" ->
        # what the machine ran is the program's beginning: no block skipped or repeated
        if drip do
          assert drip.received <= byte_size(text) and
                   drip.crc == Vws.Codecs.CRC16.compute(binary_part(text, 0, drip.received)),
                 "a block skipped or repeated, flips #{inspect(flips)}: #{inspect(drip)}"
        end

        :error

      other ->
        flunk("#{inspect(other)}, flips #{inspect(flips)}")
    end
  end

  defp await_idle(link) do
    assert eventually(fn -> DNC.info(link).state == :idle end, 10_000)
  end
end
