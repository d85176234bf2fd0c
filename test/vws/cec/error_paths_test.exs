defmodule Vws.CEC.ErrorPathsTest do
  # PROTOCOLS.md §1: every ERROR text the WC sees is upper-case words and numbers, never an
  # Elixir term (issue 24: `ERROR BAD RESULT {:error, :bad_directory}` reached the WC). Beside
  # the sanitiser's own properties (test/vws/codecs/wc/words_test.exs): a module's result, exit
  # and crash end to end through the WC link, every LinkError reason, and every Monarch command
  # against a link that answers errors or garbage.
  use ExUnit.Case, async: true
  use Vws.PropCase
  import ExUnit.CaptureLog

  alias Vws.Codecs.WC.Words
  alias Vws.Links.DNC.LinkError
  alias Vws.Test.WCPeer

  defp words?(text), do: is_binary(text) and text != "" and Words.text?(text)

  defp status_ok?(:done), do: true
  defp status_ok?({:error, text}), do: words?(text)
  defp status_ok?(_), do: false

  # any term, the odd ones included: pids, references, functions, exceptions, structs, improper
  # lists, invalid UTF-8
  defp term do
    :proper_types.oneof([
      :proper_types.any(),
      {:error, :proper_types.any()},
      {:error, :proper_types.binary()},
      {:error, :proper_types.list(:proper_types.integer(0, 0x10FFFF))},
      :proper_types.exactly(self()),
      :proper_types.exactly(make_ref()),
      :proper_types.exactly(&Enum.map/2),
      :proper_types.exactly(%RuntimeError{message: "boom {:x, 1}"}),
      :proper_types.exactly(%LinkError{reason: :no_reply, block: 3, count: 3}),
      :proper_types.exactly(%{"k" => {"v", 2.5}, a: [1 | :b]}),
      :proper_types.exactly({:error, <<255, 0, 128>>})
    ])
  end

  defp to_text(chars) when is_list(chars) do
    if Enum.all?(chars, &(is_integer(&1) and &1 in 0..0x10FFFF)),
      do: chars |> Enum.reject(&(&1 in 0xD800..0xDFFF)) |> List.to_string(),
      else: chars
  end

  defp to_text(other), do: other

  describe "end to end: what the WC reads" do
    setup do
      %{ws: ws, wc: wc} =
        Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot())

      {:ok, peer} = WCPeer.connect(wc)
      %{ws: ws, peer: peer}
    end

    defp seq, do: rem(System.unique_integer([:positive]), 10_000)

    # one ROBOT command through the WC link, ended by `finish` (the held command's pid given),
    # and its status as the WC reads it
    defp robot(peer, number, text, finish) do
      s = seq()
      WCPeer.send_string(peer, s, [{"R", number, text}])
      assert Vws.Codecs.WC.Reply.decode(WCPeer.recv_line(peer)) == {:ok, {:ack, s}}

      if finish do
        assert_receive {:executing, pid, ^number, _}, 5_000
        finish.(pid)
      end

      status = WCPeer.await_status(peer, 1, "ROBOT_CMD", &(not (&1 =~ "EXECUTING")), 10_000)
      <<_::binary-4, word::binary>> = status
      word
    end

    defp wc_ok?("DONE"), do: true
    defp wc_ok?("ERROR " <> text), do: words?(text)
    defp wc_ok?(_), do: false

    test "property: any result, any exit, a crash — the WC reads DONE or ERROR in words", %{
      peer: peer
    } do
      how = :proper_types.elements([:result, :exit, :kill])

      property =
        :proper.forall({term(), how}, fn {t, how} ->
          t = with {:error, chars} when is_list(chars) <- t, do: {:error, to_text(chars)}
          number = rem(System.unique_integer([:positive]), 9_999) + 1

          finish =
            case how do
              :result -> &send(&1, {:result, t})
              :exit -> &Process.exit(&1, {:shutdown, t})
              :kill -> &Process.exit(&1, :kill)
            end

          {word, _log} = with_log(fn -> robot(peer, number, "HOLD #{number}", finish) end)
          wc_ok?(word)
        end)

      assert_property(property, 60)

      {word, _log} = with_log(fn -> robot(peer, 42, "CRASH", nil) end)
      assert word =~ ~r/^ERROR CRASHED DELIBERATE CRASH$|^ERROR .*DELIBERATE CRASH/
      assert wc_ok?(word)
    end
  end

  describe "MONARCH's DNC errors" do
    @reasons [
      :link_down,
      :no_answer_to_bid,
      :contention,
      :nak_limit,
      :no_reply,
      :wack_limit,
      :aborted,
      :no_response,
      :receive_timeout,
      :too_large,
      :timeout,
      :invalid_text
    ]

    defp link_error do
      :proper_types.bind(
        {:proper_types.oneof([:proper_types.elements(@reasons), :proper_types.atom()]),
         :proper_types.oneof([:proper_types.exactly(nil), :proper_types.non_neg_integer()]),
         :proper_types.oneof([:proper_types.exactly(nil), :proper_types.integer()])},
        fn {reason, block, count} -> %LinkError{reason: reason, block: block, count: count} end,
        false
      )
    end

    test "property: every LinkError reason (and one we do not know) is said in words" do
      property = :proper.forall(link_error(), &words?(LinkError.status_text(&1)))
      assert_property(property, 500)
    end

    # A stand-in for the DNC link: answers every request from a script (an error, or blocks of
    # random bytes: a report, a directory, a program that cannot be read) and its info.
    defp fake_link(script) do
      spawn_link(fn -> fake_loop(script) end)
    end

    defp fake_loop(script) do
      receive do
        {:"$gen_call", from, :info} ->
          # (with its counters, as Vws.Links.DNC.info/1: the transfer history reads them)
          GenServer.reply(from, %{max_text: 256, counters: %{}})
          fake_loop(script)

        # Vws.Links.DNC.request/4 casts the request with the caller's deadline and a reply
        # address (Vws.Links.Connection)
        {:"$gen_cast", {Vws.Links.Connection, from, _deadline, {:request, _command, _blocks}}} ->
          [answer | rest] = script
          GenServer.reply(from, answer)
          fake_loop(rest ++ [answer])

        :stop ->
          :ok
      end
    end

    @commands [
      "STATUS",
      "DOWNLOAD_GE",
      "DOWNLOAD_GE(000055.PRO)",
      "DOWNLOAD_GE(000055.PRO/2)",
      "UPLOAD_GE(000055.PRO)",
      "PROGRAM_SELECT(000055)",
      "PROGRAM_DELETE(000055.PRO)",
      "TABLE(1/2/3)",
      "COMPARE_GE",
      "COMPARE_GE(000055.PRO)",
      "DRIP_FEED",
      "DRIP_FEED(000055.PRO)",
      "DRIP_FEED(000055.PRO/2/N3)",
      "RELEASE_TABLE"
    ]

    test "property: every Monarch command, whatever the link answers, ends DONE or ERROR in words" do
      %{ws: ws} = Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot())
      :ok = Vws.CEC.Mailbox.put_nc_file(ws, ["%", "O55", "N10 G01 X1", "%"])

      answer =
        :proper_types.oneof([
          {:error, link_error()},
          {:ok, :proper_types.list(:proper_types.binary())},
          {:ok,
           :proper_types.exactly(["STATE=IDLE;PROG=000055;ALARM=0", "000055.PRO 1330000 0F0F\n"])},
          {:ok, :proper_types.exactly(["STATE=IDLE;PROG=000055;ALARM=7"])}
        ])

      property =
        :proper.forall(
          {:proper_types.elements(@commands),
           :proper_types.non_empty(:proper_types.list(answer))},
          fn {text, script} ->
            link = fake_link(script)
            {:ok, command} = Vws.Partitions.Monarch.parse(text)
            ctx = %{workstation: ws, link: link, options: [start_timeout: 0, poll_interval: 1]}
            {result, _log} = with_log(fn -> Vws.Partitions.Monarch.execute(command, ctx) end)
            send(link, :stop)
            status_ok?(result) or (IO.inspect({text, script, result}) && false)
          end
        )

      assert_property(property, 300)
    end
  end
end
