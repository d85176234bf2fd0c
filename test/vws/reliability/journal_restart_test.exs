defmodule Vws.Reliability.JournalRestartTest do
  # Issue 24 B, "Restart after anything the WC sent": random WC sessions — valid strings, every
  # rule of the Parser broken, garbage, bad BCCs, unknown sets and commands, retransmissions,
  # status queries, transfers begun and left — then the workstation is killed or stopped, and
  # it starts again with every status as before (what was EXECUTING interrupted), nothing run
  # twice.
  use ExUnit.Case, async: true
  use Vws.PropCase

  import :proper_types

  alias Vws.CEC.{Mailbox, Workstation}
  alias Vws.CEC.SunComm.Status
  alias Vws.Test.{Eventually, WCPeer}

  @moduletag :tmp_dir
  @moduletag timeout: 300_000

  @names Vws.Codecs.WC.Status.names() ++ ["Q_CMD", "Z_CMD", "K_CMD"]

  defp start_ws(id, dir) do
    opts = [
      id: id,
      wc: "loopback:wc-#{id}",
      journal: [dir: dir],
      partitions: Vws.Test.Workstation.held_robot()
    ]

    start_supervised!({Workstation, opts}, id: id)
  end

  defp text, do: elements(["OPEN", "CLOSE", "ON", "OFF", "HOLD 1", "WHERE", "NONSENSE 12"])

  defp monarch_text,
    do: elements(["CYCLE_START", "DOWNLOAD_HP", "UPLOAD_SUN", "UPLOAD_GE(000001.PRO)", "X"])

  defp command do
    oneof([
      tuple([elements(["R", "G", "F", "V", "H"]), range(0, 9999), text()]),
      tuple([exactly("M"), range(0, 9999), monarch_text()]),
      # unknown sets
      tuple([elements(["Q", "Z", "K"]), range(0, 9999), text()]),
      tuple([exactly("A"), range(0, 9999), text()])
    ])
  end

  defp line do
    oneof([
      # valid, or rule 1 broken (a letter twice) by chance
      tuple([exactly(:string), resize(4, non_empty(list(command())))]),
      # rule 2 broken: a status command with others
      tuple([exactly(:string), bind(list(command()), &exactly([{"S", 1, "VISE"} | &1]), false)]),
      tuple([exactly(:string), exactly([{"S", 2, "GRIPPER_CMD"}])]),
      tuple([exactly(:string), exactly([{"S", 3, "NO_SUCH_STATUS"}])]),
      tuple([exactly(:garbage), resize(40, list(range(0x20, 0x7E)))]),
      exactly(:bad_bcc),
      exactly(:again)
    ])
  end

  defp send_line(peer, {:string, commands}, seq, _last) do
    commands = for {l, n, t} <- commands, do: {l, n, String.replace(t, "*", "")}
    line = WCPeer.string(seq, commands)
    :ok = WCPeer.send_raw(peer, line)
    line
  end

  defp send_line(peer, {:garbage, chars}, _seq, last) do
    WCPeer.send_line(peer, List.to_string(chars))
    last
  end

  defp send_line(peer, :bad_bcc, seq, last) do
    line = WCPeer.string(seq, [{"G", 1, "OPEN"}]) |> String.trim_trailing("\r\n")
    WCPeer.send_line(peer, String.slice(line, 0..-4) <> "999")
    last
  end

  defp send_line(peer, :again, seq, nil),
    do: send_line(peer, {:string, [{"V", 1, "ON"}]}, seq, nil)

  defp send_line(peer, :again, _seq, last) do
    :ok = WCPeer.send_raw(peer, last)
    last
  end

  defp answers(id), do: Map.new(@names, &{&1, Status.answer(id, &1)})

  # what the restarted workstation must answer: the same, a command under way interrupted
  defp after_restart(answers) do
    Map.new(answers, fn {name, text} ->
      {name, String.replace(text, ~r/^(\d{4})EXECUTING$/, "\\1ERROR INTERRUPTED BY RESTART")}
    end)
  end

  defp settled?(id, p) do
    Mailbox.command_status(id, p) |> elem(1) != :executing or
      (p == :robot and match?({_, "HOLD" <> _}, Mailbox.cmd_in(id, :robot)))
  end

  defp listening?(id) do
    Vws.CEC.SunComm.listening(id) != nil
  catch
    :exit, _ -> false
  end

  defp flush_executing do
    receive do
      {:executing, _, _, _} -> flush_executing()
    after
      0 -> :ok
    end
  end

  test "after any WC session, killed or stopped, the workstation starts again with every status as before",
       %{tmp_dir: dir} do
    property =
      :proper.forall(
        tuple([resize(12, list(line())), elements([:kill, :stop])]),
        fn {lines, how} ->
          reporting(fn ->
            id = "session-#{System.unique_integer([:positive])}"
            jdir = Path.join(dir, id)
            sup = start_ws(id, jdir)
            {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")

            Enum.reduce(Enum.with_index(lines, 1), nil, fn {l, seq}, last ->
              last = send_line(peer, l, seq, last)
              # every line is answered: 05A, E or a status
              assert is_binary(WCPeer.recv_line(peer, 10_000))
              last
            end)

            # SUN_COMM acknowledges a string before it runs its rules and dispatches its
            # commands: one more round trip, and every command of the session is handed over
            WCPeer.status(peer, 9999, 9, "ROBOT_CMD")
            WCPeer.close(peer)

            # the commands that can end have ended (a HOLD of the held robot stays EXECUTING)
            assert Eventually.eventually(
                     fn ->
                       Enum.all?(Mailbox.partitions(), &settled?(id, &1))
                     end,
                     15_000
                   )

            before = answers(id)
            last_string = Mailbox.last_string(id)

            log =
              ExUnit.CaptureLog.capture_log(fn ->
                case how do
                  :kill ->
                    Process.exit(sup, :kill)

                    assert Eventually.eventually(
                             fn ->
                               Workstation.whereis(id) not in [nil, sup] and listening?(id)
                             end,
                             15_000
                           )

                  :stop ->
                    :ok = stop_supervised(id)
                    start_ws(id, jdir)
                    assert Eventually.eventually(fn -> listening?(id) end, 15_000)
                end
              end)

            flush_executing()
            now = answers(id)
            expected = after_restart(before)

            ok? =
              now == expected and Mailbox.last_string(id) == last_string and
                not (log =~ "journal of #{inspect(id)} damaged") and
                (refute_receive({:executing, _, _, _}, 50) || true)

            :ok = stop_supervised(id)

            ok? or
              tell(
                "#{how} after #{inspect(lines)}:\n" <>
                  Enum.map_join(@names, "\n", &"#{&1}: #{expected[&1]} -> #{now[&1]}") <>
                  "\n" <> log
              )
          end)
        end
      )

    assert_property(property, 100)
  end

  test "killed at any point of a WC session, it starts again: nothing EXECUTING, nothing damaged, nothing run twice",
       %{tmp_dir: dir} do
    property =
      :proper.forall(
        tuple([resize(12, non_empty(list(line()))), range(0, 1_000)]),
        fn {lines, at} ->
          reporting(fn ->
            id = "midkill-#{System.unique_integer([:positive])}"
            jdir = Path.join(dir, id)
            sup = start_ws(id, jdir)
            {:ok, peer} = WCPeer.connect("loopback:wc-#{id}")
            stop_at = rem(at, length(lines)) + 1

            # the lines up to the chosen one, the last of them unanswered when the node dies
            Enum.reduce_while(Enum.with_index(lines, 1), nil, fn {l, seq}, last ->
              last = send_line(peer, l, seq, last)

              if seq == stop_at,
                do: {:halt, last},
                else:
                  {:cont,
                   (
                     WCPeer.recv_line(peer, 10_000)
                     last
                   )}
            end)

            log =
              ExUnit.CaptureLog.capture_log(fn ->
                Process.exit(sup, :kill)

                assert Eventually.eventually(
                         fn -> Workstation.whereis(id) not in [nil, sup] and listening?(id) end,
                         15_000
                       )
              end)

            flush_executing()
            now = answers(id)

            bad =
              for p <-
                    ~w(ROBOT_CMD MONARCH_CMD GRIPPER_CMD FIXTURE_CMD VACUUM_CMD HYDRAULIC_CMD Q_CMD Z_CMD K_CMD),
                  not (now[p] =~ ~r/^\d{4}(NONE|DONE|ERROR [A-Z0-9 #().,:\/_-]+)$/),
                  do: {p, now[p]}

            ok? =
              bad == [] and not (log =~ "journal of #{inspect(id)} damaged") and
                (refute_receive({:executing, _, _, _}, 50) || true)

            WCPeer.close(peer)
            :ok = stop_supervised(id)
            ok? or tell("killed at line #{stop_at} of #{inspect(lines)}: #{inspect(bad)}\n#{log}")
          end)
        end
      )

    assert_property(property, 60)
  end

  # PropEr of this OTP cannot report an exception in a property (erlang:get_stacktrace/0)
  defp reporting(fun) do
    fun.()
  rescue
    e ->
      IO.puts(Exception.format(:error, e, __STACKTRACE__))
      false
  end

  defp tell(text) do
    IO.puts(text)
    false
  end
end
