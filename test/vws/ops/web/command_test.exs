defmodule Vws.Ops.Web.CommandTest do
  use ExUnit.Case, async: true

  alias Vws.Ops.Web.Command
  alias Vws.Test.{JSONDecode, WCPeer}

  defp web(opts) do
    pid = start_supervised!({Vws.Ops.Web, [port: 0] ++ opts}, id: make_ref())
    Vws.Ops.Web.url(pid)
  end

  defp post(url, body, headers) do
    {:ok, {{_, status, _}, _h, answer}} =
      :httpc.request(
        :post,
        {String.to_charlist(url <> "api/command"), headers, ~c"application/json", body},
        [timeout: 30_000],
        body_format: :binary
      )

    {status, JSONDecode.decode(answer)}
  end

  defp token, do: [{~c"x-vws-token", ~c"s3cret"}]

  defp body(ws, set, text),
    do: ~s({"workstation": "#{ws}", "set": "#{set}", "text": "#{text}"})

  test "only the operator's commands are allowed" do
    for {set, text} <- [
          {"M", "DOWNLOAD_GE(001234.PRO/2)"},
          {"M", "DOWNLOAD_GE(001234.PRO)"},
          {"M", "COMPARE_GE(001234.PRO)"},
          {"M", "UPLOAD_GE(000100.PRO)"},
          {"M", "DRIP_FEED"},
          {"M", "DRIP_FEED(001234.PRO)"},
          {"M", "DRIP_FEED(001234.PRO/7)"},
          {"M", "DRIP_FEED(001234.PRO/N600)"},
          {"M", "DRIP_FEED(001234.PRO/999999/N9999999)"},
          {"M", "RELEASE_TABLE"},
          {"R", "RELEASE_TABLE"},
          {"R", "RELEASE_TRAY1"},
          {"R", "RELEASE_TRAY2"},
          {"F", "RELEASE_TABLE"}
        ],
        do: assert(Command.allowed?(set, text), "#{set} #{text}")

    for {set, text} <- [
          {"M", "DOWNLOAD_HP"},
          {"M", "UPLOAD_SUN"},
          {"M", "CYCLE_START"},
          {"M", "DOWNLOAD_GE(1234.PRO)"},
          {"M", "DRIP_FEED*M0001CYCLE_START"},
          {"M", "DRIP_FEED(001234.PRO/N600/7)"},
          {"M", "DRIP_FEED(001234.PRO/7/FORCE)"},
          {"M", "DRIP_FEED(001234.GSU)"},
          {"M", "DRIP_FEED(1234.PRO/N5)"},
          {"M", "DRIP_FEED(001234.PRO/N)"},
          {"R", "DO MOVE NOWHERE"},
          {"R", "RELEASE_TRAY3"},
          {"F", "RELEASE_TRAY1"},
          {"G", "OPEN"},
          {"S", "ROBOT_CMD"},
          {"m", "DRIP_FEED"},
          {"M", "DRIP_FEED\r\n"},
          {"M", "DRIP_FEED\n"},
          {"R", "RELEASE_TRAY1\n"}
        ],
        do: refute(Command.allowed?(set, text), "#{inspect(set)} #{inspect(text)}")
  end

  test "the body: a flat JSON object of strings, escapes decoded, anything else refused" do
    assert {:ok, %{"a" => "x\"y/", "b" => "é"}} =
             Command.decode(~s( {"a" : "x\\"y\\/", "b":"\\u00e9"} ))

    assert {:ok, %{}} = Command.decode("{}")

    for bad <- [
          "",
          "[]",
          ~s({"a": 1}),
          ~s({"a": "b"),
          ~s({"a": "b"} x),
          ~s({"a" "b"}),
          "{\"a\":\"\n\"}"
        ],
        do: assert(Command.decode(bad) == :error, inspect(bad))
  end

  test "through HTTP: the control token, the whitelist and a bounded body", %{} do
    %{ws: ws} = Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot())
    read_only = web([])
    url = web(token: "s3cret")

    assert {403, %{"error" => "read-only: no control token configured"}} =
             post(read_only, body(ws, "R", "RELEASE_TABLE"), token())

    assert {403, _} = post(url, body(ws, "R", "RELEASE_TABLE"), [])
    assert {403, _} = post(url, body(ws, "R", "RELEASE_TABLE"), [{~c"x-vws-token", ~c"s3cre"}])

    assert {400, %{"error" => "not an operator command: R DO MOVE NOWHERE"}} =
             post(url, body(ws, "R", "DO MOVE NOWHERE"), token())

    assert {400, %{"error" => "needs a JSON object with workstation, set and text"}} =
             post(url, "not json", token())

    assert {404, %{"error" => "no workstation nope"}} =
             post(url, body("nope", "R", "RELEASE_TABLE"), token())

    big = body(ws, "R", "RELEASE_TABLE" <> String.duplicate(" ", Command.max_body()))
    assert {413, _} = post(url, big, token())
  end

  test "a command runs through SUN_COMM's path: its partition, interlocks, status and journal" do
    %{ws: ws, wc: wc} = Vws.Test.Workstation.start(partitions: Vws.Test.Workstation.held_robot())
    url = web(token: "s3cret")
    {:ok, peer} = WCPeer.connect(wc)
    WCPeer.send_string(peer, 1, [{"R", 7, "HOLD AT TRAY"}])
    assert "05A0001" <> _ = WCPeer.recv_line(peer)
    assert_receive {:executing, held, 7, _}, 5_000
    last = Vws.CEC.Mailbox.last_string(ws)

    # ROBOT busy with the WC's command: the page's is refused as the WC's would be
    assert {200, %{"number" => "9" <> _ = n, "status" => "ERROR BUSY 0007"}} =
             post(url, body(ws, "R", "RELEASE_TABLE"), token())

    number = String.to_integer(n)
    assert {^number, {:error, "BUSY 0007"}} = Vws.CEC.Mailbox.command_status(ws, :robot)

    # (the WC's command 7 ends; the status location keeps the newer answer, as for a WC's BUSY)
    send(held, {:result, :done})
    await_free(ws, :robot)

    # ROBOT free: the partition takes it and judges it (this test robot knows no RELEASE_TABLE)
    before = DateTime.utc_now()

    assert {200, %{"number" => n2, "time" => time}} =
             post(url, body(ws, "R", "RELEASE_TABLE"), token())

    # when it was taken, for the page to tell a state read before it (Vws.Ops.Web.Page)
    assert {:ok, taken, 0} = DateTime.from_iso8601(time)
    assert DateTime.compare(taken, DateTime.truncate(before, :millisecond)) != :lt
    number2 = String.to_integer(n2)
    assert number2 != number
    assert_receive_status(ws, :robot, number2, :error)

    # the WC's link is untouched: its last string (rule 4) is the same, nothing was sent to it
    assert Vws.CEC.Mailbox.last_string(ws) == last
    assert {:timeout, _} = WCPeer.recv_line(peer, 300)

    # the history has the page's commands and what became of them, with the node's time
    history = Vws.Ops.Web.History.recent(ws)

    assert Enum.any?(
             history,
             &(&1.where == "OPERATOR" and &1.text =~ "R#{n2} RELEASE_TABLE sent")
           )

    assert Enum.any?(history, &(&1.where == "ROBOT" and &1.text =~ ~r/^#{n2} ERROR/))
    assert Enum.all?(history, &match?({:ok, _, 0}, DateTime.from_iso8601(&1.time)))
  end

  defp await_free(ws, partition, tries \\ 100) do
    cond do
      Vws.CEC.Mailbox.in_flight(ws, partition) == nil -> :ok
      tries == 0 -> flunk("#{partition} still busy")
      true -> Process.sleep(50) && await_free(ws, partition, tries - 1)
    end
  end

  defp assert_receive_status(ws, partition, number, pattern, tries \\ 100) do
    case Vws.CEC.Mailbox.command_status(ws, partition) do
      {^number, status} when status != :executing ->
        if pattern == :error,
          do: assert({:error, _} = status),
          else: assert(status == pattern)

      _ when tries > 0 ->
        Process.sleep(50)
        assert_receive_status(ws, partition, number, pattern, tries - 1)

      other ->
        flunk("#{partition} #{number} did not end: #{inspect(other)}")
    end
  end
end
