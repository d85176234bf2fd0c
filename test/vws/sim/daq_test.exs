defmodule Vws.Sim.DAQTest do
  use ExUnit.Case, async: true

  alias Vws.Sim.{DAQ, Plant}
  alias Vws.Links.Transport

  doctest Vws.Sim.DAQ

  # The test is the CEC: a raw TCP client that sends lines and reads lines.
  setup do
    plant = start_supervised!({Plant, time_scale: 0, seed: 5}, id: :plant)
    daq = start_supervised!({DAQ, plant: plant}, id: :daq)
    {:ok, conn} = Transport.connect(DAQ.endpoint(daq))
    %{plant: plant, daq: daq, conn: conn}
  end

  defp ask(conn, line) do
    :ok = Transport.send(conn, [line, "\n"])
    recv(conn)
  end

  defp recv(conn, acc \\ "") do
    if String.ends_with?(acc, "\n") do
      String.trim_trailing(acc, "\n")
    else
      :ok = Transport.activate(conn)

      case Vws.TransportHelpers.next(conn, 2_000) do
        {:data, bytes} -> recv(conn, acc <> bytes)
        :timeout -> {:no_answer, acc}
      end
    end
  end

  defp silent?(conn, ms) do
    :ok = Transport.activate(conn)

    receive do
      msg -> flunk("unexpected answer #{inspect(Transport.handle_message(conn, msg))}")
    after
      ms -> true
    end
  end

  test "identifies itself", %{conn: conn} do
    assert ask(conn, "*IDN?") == "NBS-VWS-SIM,34970A,daq1,1.0"
  end

  test "measures the plant's channels as SCPI readings", %{conn: conn, plant: plant} do
    :ok = Plant.set_part(plant, :vise, true)
    readings = ask(conn, "MEAS:VOLT:DC? (@101:116)") |> String.split(",")
    assert length(readings) == 16
    assert Enum.all?(readings, &(&1 =~ ~r/^[+-]\d\.\d{8}E[+-]\d\d$/))
    # 101 part present (5 V), 102 vise fully open (5 V), 103 jaw pot at 150 mm = 8.0 V
    [v101, v102, v103 | _] = Enum.map(readings, &String.to_float/1)
    assert_in_delta v101, 5.0, 0.02
    assert_in_delta v102, 5.0, 0.02
    assert_in_delta v103, 8.0, 0.005
    [ohms] = ask(conn, "MEAS:RES? (@117)") |> String.split(",") |> Enum.map(&String.to_float/1)
    assert_in_delta ohms, 350.0, 0.05
  end

  test "routes relays to the plant and reports them", %{conn: conn, plant: plant} do
    :ok = Transport.send(conn, "ROUT:CLOS (@206,207)\n")
    assert ask(conn, "ROUT:CLOS? (@205:207)") == "0,1,1"
    assert {:daq1, 206} in Plant.snapshot(plant).relays
    :ok = Transport.send(conn, "rout:open (@207)\n")
    assert ask(conn, "ROUT:CLOS? (@207)") == "0"
    :ok = Transport.send(conn, "*RST\n")
    assert ask(conn, "ROUT:CLOS? (@206)") == "0"
  end

  test "bad lines are not answered: the error queue says why", %{conn: conn, plant: plant} do
    :ok = Transport.send(conn, "MEAS:VOLT:DC? (@201)\nFOO?\nROUT:CLOS (@206,103)\n")
    assert silent?(conn, 50)
    assert ask(conn, "SYST:ERR?") == ~s(-221,"Settings conflict")
    assert ask(conn, "SYST:ERR?") == ~s(-113,"Undefined header")
    assert ask(conn, "SYST:ERR?") == ~s(-221,"Settings conflict")
    assert ask(conn, "SYST:ERR?") == ~s(+0,"No error")
    # all or nothing: 206 was not closed either
    assert Plant.snapshot(plant).relays == []
    # a hydraulic-controller command is not a DAQ's
    :ok = Transport.send(conn, "CLAMP_PALLET\n")
    assert ask(conn, "SYST:ERR?") == ~s(-113,"Undefined header")
  end

  test "the error queue holds 20 and then says it overflowed", %{conn: conn} do
    :ok = Transport.send(conn, String.duplicate("BOGUS\n", 25))
    errors = for _ <- 1..21, do: ask(conn, "SYST:ERR?")
    assert Enum.take(errors, 19) == List.duplicate(~s(-113,"Undefined header"), 19)
    assert Enum.at(errors, 19) == ~s(-350,"Queue overflow")
    assert Enum.at(errors, 20) == ~s(+0,"No error")
  end

  test "mute: it takes lines and does nothing; healed, it answers again", %{
    conn: conn,
    daq: daq,
    plant: plant
  } do
    :ok = DAQ.set_fault(daq, :mute)
    :ok = Transport.send(conn, "ROUT:CLOS (@207)\n*IDN?\n")
    assert silent?(conn, 100)
    assert Plant.snapshot(plant).relays == []
    :ok = DAQ.set_fault(daq, :none)
    assert ask(conn, "ROUT:CLOS? (@207)") == "0"
    assert %{lines: 3, answered: 1} = DAQ.info(daq)
  end

  test "delay: answers come late but in order", %{conn: conn, daq: daq} do
    :ok = DAQ.set_fault(daq, {:delay_ms, 30})
    t0 = System.monotonic_time(:millisecond)
    assert ask(conn, "*IDN?") =~ "34970A"
    assert System.monotonic_time(:millisecond) - t0 >= 30
  end

  test "several connections, each with its own answers; dropped ones can reconnect",
       %{conn: conn, daq: daq} do
    {:ok, other} = Transport.connect(DAQ.endpoint(daq))
    assert ask(other, "ROUT:CLOS? (@201)") == "0"
    assert ask(conn, "*IDN?") =~ "NBS-VWS-SIM"
    :ok = DAQ.drop_connections(daq)
    # (the other connection's close comes too: each is taken for its own)
    Vws.TransportHelpers.assert_closed(conn)
    Vws.TransportHelpers.assert_closed(other)
    {:ok, again} = Transport.connect(DAQ.endpoint(daq))
    assert ask(again, "*IDN?") =~ "NBS-VWS-SIM"
  end
end
