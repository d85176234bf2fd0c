defmodule Vws.Sim.VAL2SessionTest do
  use ExUnit.Case, async: true

  alias Vws.Links.DDCMP
  alias Vws.Sim.VAL2
  alias Vws.Links.VAL.Message
  import Vws.Test.Eventually

  # The CEC is played by a bare DDCMP link and this test, so the order of events at the simulator
  # can be fixed: the flaky "a re-initialised link prompts again" of val2_test.exs, made certain.
  setup do
    sim = start_supervised!({VAL2, time_scale: 0.001}, id: :sim)
    cec = start_supervised!({DDCMP, endpoint: VAL2.endpoint(sim), owner: self()}, id: :cec)
    assert_receive {:ddcmp, ^cec, :up}, 5000
    %{sim: sim, cec: cec}
  end

  test "an answer from the CEC that comes with the link's restart prompts nothing into the new session",
       %{sim: sim, cec: cec} do
    %Message{qualifier: prompt} = receive_message(cec, 2, :read)
    send_message(cec, %Message{lun: 2, function: :write, qualifier: prompt, text: "WHERE"})
    %Message{qualifier: response, text: "0" <> _} = receive_message(cec, 2, :write)

    # The CEC replies to the response (after which the monitor would prompt) and at once
    # re-initialises the link (seed §4.3.2). The simulator is kept from handling either until
    # both are on its line: the REPLY is handled with the restart right behind it (in the same
    # chunk of bytes, or the next), and whatever it causes must not reach the new session.
    :sys.suspend(sim)
    send_message(cec, %Message{lun: 2, function: :reply, qualifier: response})
    :ok = DDCMP.restart(cec)
    assert_receive {:ddcmp, ^cec, {:down, :restart}}
    :sys.resume(sim)
    assert_receive {:ddcmp, ^cec, :up}, 5000
    assert eventually(fn -> VAL2.info(sim).link end)

    # everything the simulator sends in the new session has reached the CEC
    assert eventually(fn -> match?(%{outstanding: 0, queue: 0}, VAL2.info(sim).line) end)
    new_session = drain(cec)

    # the start-up prompts once, and only once
    assert [%Message{qualifier: prompt}] = for(%Message{lun: 2} = m <- new_session, do: m)
    assert %Message{function: :read} = hd(for %Message{lun: 2} = m <- new_session, do: m)

    # and the command answering it is obeyed
    send_message(cec, %Message{lun: 2, function: :write, qualifier: prompt, text: "WHERE"})
    assert %Message{text: "0" <> _} = receive_message(cec, 2, :write)
    info = VAL2.info(sim)
    assert info.commands == ["WHERE", "WHERE"]
    assert info.violations == 0 and info.stale == 0
  end

  # never held for a later session: refused (and the test fails) unless the link is RUNNING
  defp send_message(cec, message),
    do: :ok = DDCMP.send_data(cec, Message.encode(message), hold: false)

  # the next message on `lun` with `function`; others are skipped (LUN 1's status is replied to)
  defp receive_message(cec, lun, function) do
    receive do
      {:ddcmp, ^cec, {:data, bytes}} ->
        case Message.decode(bytes) do
          {:ok, %Message{lun: ^lun, function: ^function} = m} ->
            m

          {:ok, %Message{lun: 1, function: :write} = m} ->
            send_message(cec, %Message{lun: 1, function: :reply, qualifier: m.qualifier})
            receive_message(cec, lun, function)

          other ->
            flunk("unexpected #{inspect(other)}")
        end
    after
      5000 -> flunk("no LUN #{lun} #{function} from the simulator")
    end
  end

  defp drain(cec) do
    receive do
      {:ddcmp, ^cec, {:data, bytes}} ->
        {:ok, m} = Message.decode(bytes)
        [m | drain(cec)]
    after
      0 -> []
    end
  end
end
