defmodule Vws.Reliability.WCRoundTripFlipTest do
  @moduledoc """
  A whole round trip WC → CEC → GE-2000 → CEC → WC (DOWNLOAD_HP, DOWNLOAD_GE, UPLOAD_GE,
  UPLOAD_SUN) over the real WC TCP link, with a relay between a real `Vws.Peers.WC.Client` and
  SUN_COMM's TCP listener flipping a bit in transfer answers in both directions — the CEC's
  `Annnn` to the WC's program lines, the WC's `Annnn` to the CEC's — and in program lines
  (issue 15). The program comes back byte-identical.
  """
  use ExUnit.Case, async: true

  alias Vws.Links.DNC
  alias Vws.CEC.{Mailbox, SunComm, Workstation}
  alias Vws.Sim.GE2000
  alias Vws.Test.FlipRelay
  alias Vws.Peers.WC.Client
  import Vws.Test.Eventually

  @moduletag timeout: 300_000

  @answer ~r/^A\d{7}\r?$/
  @program_line ~r/^\d{4}[^*]*\d{3}\r?$/

  test "answers flipped both ways: the program comes back byte-identical" do
    sim = start_supervised!({GE2000, link: [reply_timeout: 300]})

    %{ws: ws} =
      Vws.Test.Workstation.start(
        wc: "tcp://127.0.0.1:0",
        devices: [ge2000: [endpoint: GE2000.endpoint(sim), reply_timeout: 300]]
      )

    assert eventually(fn -> DNC.info(Workstation.whereis(ws, :ge2000)).state == :idle end)
    wc = eventually_value(fn -> SunComm.listening(ws) end)
    {:ok, relay} = FlipRelay.start_link(to_string(wc))

    program =
      ["%", "O000815 (ROUND TRIP)"] ++
        for(n <- 1..150, do: "N#{n * 10} G01 X#{n}.#{rem(n * 7, 10)} Y-#{n * 3} F250") ++
        ["M30", "%"]

    # every other answer and every fifth program line, each way, has one bit inverted
    seed = :erlang.phash2(self())
    :rand.seed(:exsss, {seed, 15, 2026})

    every = fn k ->
      counter = :counters.new(1, [])

      fn ->
        :counters.add(counter, 1, 1)
        rem(:counters.get(counter, 1), k) == 0
      end
    end

    answers_in = every.(2)
    answers_out = every.(2)
    lines_in = every.(5)
    lines_out = every.(5)

    flip_if = fn due? ->
      fn line ->
        if due?.() do
          body = byte_size(String.trim_trailing(line, "\r"))
          FlipRelay.flip(line, :rand.uniform(body) - 1, :rand.uniform(8) - 1)
        else
          line
        end
      end
    end

    :ok =
      FlipRelay.plan(
        relay,
        {:lines,
         [
           {:to_client, @answer, flip_if.(answers_out)},
           {:to_target, @answer, flip_if.(answers_in)},
           {:to_client, @program_line, flip_if.(lines_out)},
           {:to_target, @program_line, flip_if.(lines_in)}
         ]}
      )

    {:ok, client} =
      Client.connect(FlipRelay.endpoint(relay), reply_timeout: 500, line_timeout: 500)

    assert {:ok, {"M", 1}} = Client.download_program(client, program)
    assert :done = Client.await_command(client, "M", 1, 30_000)
    assert Mailbox.nc_file(ws) == program

    assert {:ok, [{"M", 2}]} = Client.send_commands(client, [{"M", "DOWNLOAD_GE"}])
    assert :done = Client.await_command(client, "M", 2, 60_000)
    assert {:ok, [{"M", 3}]} = Client.send_commands(client, [{"M", "UPLOAD_GE(000815.PRO)"}])
    assert :done = Client.await_command(client, "M", 3, 60_000)

    assert {:ok, {"M", 4}, uploaded} = Client.upload_program(client)
    assert :done = Client.await_command(client, "M", 4, 30_000)

    # byte-identical, after damage both ways that the two ends saw and repaired
    assert IO.iodata_to_binary(Enum.map(uploaded, &[&1, "\n"])) ==
             IO.iodata_to_binary(Enum.map(program, &[&1, "\n"]))

    assert FlipRelay.counts(relay).flips > 100
    counters = Client.info(client).counters
    assert counters.resends > 20 and counters.naks_sent > 10 and counters.lines_again > 10
    assert SunComm.info(ws).counters.lines_again > 10
  end

  defp eventually_value(fun, tries \\ 200) do
    case fun.() do
      nil when tries > 0 -> Process.sleep(10) && eventually_value(fun, tries - 1)
      value -> value
    end
  end
end
