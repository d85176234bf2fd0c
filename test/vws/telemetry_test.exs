defmodule Vws.TelemetryTest do
  use ExUnit.Case, async: false

  alias Vws.Telemetry

  test "execute reaches attached handlers; detach stops it" do
    me = self()
    id = make_ref()

    :ok =
      Telemetry.attach(
        id,
        [:vws, :test, :point],
        fn e, m, md, c -> send(me, {e, m, md, c}) end,
        :cfg
      )

    assert {:error, :already_exists} =
             Telemetry.attach(id, [:vws, :test, :point], fn _, _, _, _ -> :ok end, nil)

    Telemetry.execute([:vws, :test, :point], %{n: 1}, %{ws: "x"})
    assert_receive {[:vws, :test, :point], %{n: 1}, %{ws: "x"}, :cfg}
    :ok = Telemetry.detach(id)
    Telemetry.execute([:vws, :test, :point], %{n: 2}, %{})
    refute_receive {_, %{n: 2}, _, _}
    assert {:error, :not_found} = Telemetry.detach(id)
  end

  test "listened? says whether an event has a handler, before and after" do
    event = [:vws, :test, :listened]
    id = make_ref()
    refute Telemetry.listened?(event)
    :ok = Telemetry.attach(id, event, fn _, _, _, _ -> :ok end, nil)
    assert Telemetry.listened?(event)
    refute Telemetry.listened?([:vws, :test, :other])
    :ok = Telemetry.detach(id)
    refute Telemetry.listened?(event)
  end

  test "span emits start and stop, or exception" do
    me = self()
    id = make_ref()
    events = for s <- [:start, :stop, :exception], do: [:vws, :test, :span, s]

    :ok =
      Telemetry.attach_many(
        id,
        events,
        fn e, m, md, _ -> send(me, {List.last(e), m, md}) end,
        nil
      )

    assert Telemetry.span([:vws, :test, :span], %{a: 1}, fn -> {:result, %{a: 1, b: 2}} end) ==
             :result

    assert_receive {:start, %{monotonic_time: _}, %{a: 1}}
    assert_receive {:stop, %{duration: d}, %{b: 2}} when d >= 0

    assert_raise RuntimeError, fn ->
      Telemetry.span([:vws, :test, :span], %{a: 1}, fn -> raise "boom" end)
    end

    assert_receive {:exception, %{duration: _}, %{kind: :error}}
    Telemetry.detach(id)
  end

  test "a handler that raises is detached" do
    id = make_ref()
    :ok = Telemetry.attach(id, [:vws, :test, :bad], fn _, _, _, _ -> raise "bad handler" end, nil)
    ExUnit.CaptureLog.capture_log(fn -> Telemetry.execute([:vws, :test, :bad], %{}, %{}) end)
    assert {:error, :not_found} = Telemetry.detach(id)
  end

  test "the default handler logs every listed event" do
    :ok = Telemetry.attach_default_handler(:warning)

    log =
      ExUnit.CaptureLog.capture_log(fn ->
        Telemetry.execute([:vws, :sun_comm, :string_received], %{bytes: 10}, %{
          workstation: "W",
          sequence: 1
        })
      end)

    Telemetry.detach("vws-default-logger")
    assert log =~ "vws.sun_comm.string_received"
  end
end
