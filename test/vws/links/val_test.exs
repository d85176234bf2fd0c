defmodule Vws.Links.VALTest do
  use ExUnit.Case, async: true

  alias Vws.Test.VALPeer
  alias Vws.Links.VAL
  alias Vws.Links.VAL.Message

  doctest Vws.Links.VAL

  # The test plays the VAL II controller through a DDCMP peer of its own (`link`).
  setup do
    {:ok, link} = VALPeer.start_link()
    {:ok, val} = VAL.start_link(ddcmp: [endpoint: VALPeer.endpoint(link)])
    :ok = VALPeer.up(link)
    %{val: val, link: link}
  end

  defp deliver(link, lun, function, qualifier, text) do
    {:ok, m} = Message.new(lun, function, qualifier, text)
    VALPeer.deliver(link, Message.encode(m))
  end

  defp prompt(link), do: deliver(link, 2, :read, 0, ".")
  defp respond(link, text), do: deliver(link, 2, :write, 0, text)
  defp async(link, code, text \\ ""), do: deliver(link, 3, :write, code, text)

  defp sent(link) do
    assert_receive {:val_peer, ^link, {:sent, bin}}, 1_000
    {:ok, m} = Message.decode(bin)
    {m.lun, m.function, m.qualifier, m.text}
  end

  defp nothing_sent(link), do: refute_receive({:val_peer, ^link, {:sent, _}}, 50)

  defp run(fun), do: Task.async(fun)

  test "a command waits for the prompt, then gets its numbered response, which is replied to",
       %{val: val, link: link} do
    task = run(fn -> VAL.command(val, "WHERE", 2_000) end)
    nothing_sent(link)
    refute VAL.ready?(val)

    prompt(link)
    assert sent(link) == {2, :write, 0, "WHERE"}
    respond(link, "0 1 2 3 4 5 6 7 8 9 10 11 12")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(task) == {:ok, "1 2 3 4 5 6 7 8 9 10 11 12"}

    # no prompt yet: the next command waits for it
    task = run(fn -> VAL.command(val, "SPEED 50") end)
    nothing_sent(link)
    prompt(link)
    assert sent(link) == {2, :write, 0, "SPEED 50"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(task) == {:ok, ""}
  end

  test "the command carries the number of the prompt it answers; replies echo numbers", %{
    val: val,
    link: link
  } do
    deliver(link, 2, :read, 17, ".")
    task = run(fn -> VAL.command(val, "WHERE") end)
    assert sent(link) == {2, :write, 17, "WHERE"}
    deliver(link, 2, :write, 18, "0 W")
    assert sent(link) == {2, :reply, 18, ""}
    assert Task.await(task) == {:ok, "W"}
    deliver(link, 1, :write, 5, "MONITOR")
    assert sent(link) == {1, :reply, 5, ""}
  end

  test "a negative response is the error code and its text", %{val: val, link: link} do
    prompt(link)
    task = run(fn -> VAL.command(val, "DO MOVE NOWHERE") end)
    assert sent(link) == {2, :write, 0, "DO MOVE NOWHERE"}
    respond(link, "-301 UNDEFINED LOCATION NOWHERE")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(task) == {:error, {-301, "UNDEFINED LOCATION NOWHERE"}}
    assert VAL.info(val).state == {:idle, :still}
  end

  test "DO waits for MOTION COMPLETE; LUN 3 is replied to while LUN 2 carries on; one DO in flight",
       %{val: val, link: link} do
    prompt(link)
    move1 = run(fn -> VAL.motion(val, "DO MOVE SAFE", 5_000) end)
    assert sent(link) == {2, :write, 0, "DO MOVE SAFE"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    async(link, :motion_begin, "MOTION BEGIN")
    assert sent(link) == {3, :reply, :motion_begin, ""}
    prompt(link)

    # a second DO must wait for MOTION COMPLETE; a WHERE goes meanwhile
    move2 = run(fn -> VAL.motion(val, "DO MOVE MV1", 5_000) end)
    nothing_sent(link)
    where = run(fn -> VAL.command(val, "WHERE") end)
    assert sent(link) == {2, :write, 0, "WHERE"}
    respond(link, "0 X Y Z")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(where) == {:ok, "X Y Z"}
    prompt(link)
    nothing_sent(link)
    assert Task.yield(move1, 0) == nil

    async(link, :motion_complete, "MOTION COMPLETE")
    assert sent(link) == {3, :reply, :motion_complete, ""}
    assert Task.await(move1) == :ok

    # now the second DO goes
    assert sent(link) == {2, :write, 0, "DO MOVE MV1"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    async(link, :motion_begin)
    assert sent(link) == {3, :reply, :motion_begin, ""}
    async(link, :motion_complete)
    assert sent(link) == {3, :reply, :motion_complete, ""}
    assert Task.await(move2) == :ok
  end

  test "MOTION COMPLETE may come before the response", %{val: val, link: link} do
    prompt(link)
    move = run(fn -> VAL.motion(val, "DO DEPART 50") end)
    assert sent(link) == {2, :write, 0, "DO DEPART 50"}
    async(link, :motion_begin)
    assert sent(link) == {3, :reply, :motion_begin, ""}
    async(link, :motion_complete)
    assert sent(link) == {3, :reply, :motion_complete, ""}
    assert Task.yield(move, 50) == nil
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(move) == :ok
  end

  test "a LUN 3 ERROR during the motion ends it with the error", %{val: val, link: link} do
    prompt(link)
    move = run(fn -> VAL.motion(val, "DO MOVES VISE") end)
    assert sent(link) == {2, :write, 0, "DO MOVES VISE"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    async(link, :error, "-1002 OBSTACLE COLLISION")
    assert sent(link) == {3, :reply, :error, ""}
    assert Task.await(move) == {:error, {-1002, "OBSTACLE COLLISION"}}
    assert VAL.info(val).state == {:idle, :still}
  end

  test "EXECUTE waits for PROGRAM COMPLETE", %{val: val, link: link} do
    prompt(link)
    task = run(fn -> VAL.command(val, "EXECUTE DEBURR") end)
    assert sent(link) == {2, :write, 0, "EXECUTE DEBURR"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    async(link, :program_start, "PROGRAM START")
    assert sent(link) == {3, :reply, :program_start, ""}
    assert Task.yield(task, 50) == nil
    async(link, :program_complete, "PROGRAM COMPLETE")
    assert sent(link) == {3, :reply, :program_complete, ""}
    assert Task.await(task) == {:ok, ""}
  end

  test "request/3: the caller says what the command waits for; the text is not read for it", %{
    val: val,
    link: link
  } do
    # a program whose name a text reading could take for something else still waits for
    # PROGRAM COMPLETE, because the caller said so
    prompt(link)
    task = run(fn -> VAL.execute(val, "DO") end)
    assert sent(link) == {2, :write, 0, "EXECUTE DO"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.yield(task, 50) == nil
    async(link, :program_complete, "PROGRAM COMPLETE")
    assert sent(link) == {3, :reply, :program_complete, ""}
    assert Task.await(task) == {:ok, ""}

    # a motion said to be one waits for MOTION COMPLETE
    prompt(link)
    task = run(fn -> VAL.request(val, {:motion_complete, "DO MOVE SAFE"}, 2_000) end)
    assert sent(link) == {2, :write, 0, "DO MOVE SAFE"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.yield(task, 50) == nil
    assert VAL.info(val).state == {:idle, :moving}
    async(link, :motion_complete, "MOTION COMPLETE")
    assert sent(link) == {3, :reply, :motion_complete, ""}
    assert Task.await(task) == {:ok, ""}

    # a DO passed off as a plain monitor command would let a second motion go: refused
    assert_raise ArgumentError, fn -> VAL.request(val, {:response, "DO MOVE SAFE"}, 100) end
  end

  test "the link going down mid-command ends it ERROR; it is never re-sent", %{
    val: val,
    link: link
  } do
    prompt(link)
    move = run(fn -> VAL.motion(val, "DO MOVE SAFE") end)
    assert sent(link) == {2, :write, 0, "DO MOVE SAFE"}
    VALPeer.down(link, :too_many_failures)
    assert Task.await(move) == {:error, {:link_down, :too_many_failures}}

    VALPeer.up(link)
    prompt(link)
    nothing_sent(link)
    assert VAL.info(val).state == {:ready, :still}
  end

  test "a prompt that arrived just before the link went down lets nothing go", %{
    val: val,
    link: link
  } do
    # a request waits; the prompt and the link's end come in one chunk of bytes
    task = run(fn -> VAL.command(val, "DO MOVE SAFE", 300) end)
    assert Vws.Test.Eventually.eventually(fn -> VAL.info(val).queued == 1 end)
    {:ok, m} = Message.new(2, :read, 0, ".")
    VALPeer.deliver_and_down(link, Message.encode(m), :too_many_failures)

    nothing_sent(link)
    assert Task.await(task) == {:error, :timeout}
    assert VAL.info(val).state == {:down, :still}
  end

  test "a peer restart mid-motion ends it ERROR; the next command waits for the new prompt", %{
    val: val,
    link: link
  } do
    prompt(link)
    move = run(fn -> VAL.motion(val, "DO MOVE SAFE") end)
    assert sent(link) == {2, :write, 0, "DO MOVE SAFE"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    VALPeer.peer_restarted(link)
    assert Task.await(move) == {:error, :peer_restarted}

    where = run(fn -> VAL.command(val, "WHERE") end)
    nothing_sent(link)
    VALPeer.up(link)
    prompt(link)
    assert sent(link) == {2, :write, 0, "WHERE"}
    respond(link, "0 W")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(where) == {:ok, "W"}
  end

  test "the transport gone: waiting and new requests end :link_down at once, until it is up", %{
    val: val,
    link: link
  } do
    waiting = run(fn -> VAL.command(val, "DO MOVE SAFE", 5_000) end)
    assert Vws.Test.Eventually.eventually(fn -> VAL.info(val).queued == 1 end)
    VALPeer.down(link, :closed)
    assert Task.await(waiting) == {:error, {:link_down, :closed}}
    assert VAL.command(val, "WHERE", 5_000) == {:error, {:link_down, :closed}}

    # back: nothing of the above was kept to be sent, the next request goes
    VALPeer.up(link)
    prompt(link)
    nothing_sent(link)
    task = run(fn -> VAL.command(val, "WHERE", 2_000) end)
    assert sent(link) == {2, :write, 0, "WHERE"}
    respond(link, "0 W")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(task) == {:ok, "W"}
  end

  test "a request whose time runs out before the prompt is never sent", %{val: val, link: link} do
    assert VAL.command(val, "DO MOVE SAFE", 50) == {:error, :timeout}
    prompt(link)
    nothing_sent(link)
    assert VAL.info(val).queued == 0
  end

  test "a sent request that times out lets its late response through without confusion", %{
    val: val,
    link: link
  } do
    prompt(link)
    assert VAL.command(val, "WHERE", 50) == {:error, :timeout}
    assert sent(link) == {2, :write, 0, "WHERE"}
    respond(link, "0 LATE")
    assert sent(link) == {2, :reply, 0, ""}
    prompt(link)
    task = run(fn -> VAL.command(val, "SPEED 10") end)
    assert sent(link) == {2, :write, 0, "SPEED 10"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(task) == {:ok, ""}
  end

  test "re-initialisation restarts the link; a stale prompt does not count until it is up", %{
    val: val,
    link: link
  } do
    assert VAL.reinitialise(val) == :ok
    assert_receive {:val_peer, ^link, :restart}
    assert VAL.info(val).state == {:down, :still}
    prompt(link)
    task = run(fn -> VAL.command(val, "WHERE") end)
    nothing_sent(link)
    VALPeer.up(link)
    nothing_sent(link)
    prompt(link)
    assert sent(link) == {2, :write, 0, "WHERE"}
    respond(link, "0")
    assert sent(link) == {2, :reply, 0, ""}
    assert Task.await(task) == {:ok, ""}

    # refused while a motion is in flight
    prompt(link)
    _move = run(fn -> VAL.motion(val, "DO MOVE SAFE") end)
    assert sent(link) == {2, :write, 0, "DO MOVE SAFE"}
    assert VAL.reinitialise(val) == {:error, :busy}
  end

  test "LUN 1 short status is kept and replied to; other LUNs are never left blocked", %{
    val: val,
    link: link
  } do
    deliver(link, 1, :write, 0, "MONITOR SPEED 50")
    assert sent(link) == {1, :reply, 0, ""}
    assert VAL.info(val).short_status == "MONITOR SPEED 50"
    deliver(link, 4, :read, 0, "?")
    assert sent(link) == {4, :write, 0, ""}
    VALPeer.deliver(link, <<2, 9, 9>>)
    nothing_sent(link)
    assert VAL.info(val).counts.bad == 1
  end

  test "text that cannot be a VAL message is refused before anything is sent", %{
    val: val,
    link: link
  } do
    prompt(link)

    assert {:error, {:bad_command, %Vws.Links.VAL.Error{reason: :too_long}}} =
             VAL.command(val, String.duplicate("A", 300))

    nothing_sent(link)
  end

  test "motion/3 only takes DO instructions", %{val: val} do
    assert_raise ArgumentError, fn -> VAL.motion(val, "WHERE") end
  end

  test "the connection dying mid-motion ends it link_down; it is never re-sent", %{
    val: val,
    link: link
  } do
    prompt(link)
    move = run(fn -> VAL.motion(val, "DO MOVE SAFE") end)
    assert sent(link) == {2, :write, 0, "DO MOVE SAFE"}
    VALPeer.down(link, :closed)
    assert Task.await(move) == {:error, {:link_down, :closed}}

    # dialled again and up: the move is not sent again
    VALPeer.up(link)
    prompt(link)
    nothing_sent(link)
    assert VAL.info(val).state == {:ready, :still}
    assert %{state: :running, connected: true} = VAL.info(val).line
  end

  test "one process for the wire: the VAL process runs DDCMP itself" do
    {:ok, peer} = VALPeer.start_link()
    {:ok, val} = VAL.start_link(ddcmp: [endpoint: VALPeer.endpoint(peer)])
    :ok = VALPeer.up(peer)
    assert {:links, links} = Process.info(val, :links)
    # the caller only: no link process of its own
    assert links == [self()]
    assert VAL.info(val).line.session == 1
  end

  test "options: an unknown one or a bad DDCMP value is refused at start, naming it" do
    assert_raise Vws.Options.Error, ~r/unknown VAL option :dccmp/, fn ->
      VAL.start_link(dccmp: [endpoint: "loopback:x"])
    end

    assert_raise Vws.Options.Error, ~r/DDCMP option :window/, fn ->
      VAL.start_link(ddcmp: [endpoint: "loopback:x", window: 0])
    end
  end

  test "a request whose time runs out leaves no answer behind in the caller's mailbox", %{
    val: val
  } do
    # never sent (no prompt): the process answers :timeout at the deadline too, to an alias
    # that is gone by then
    assert VAL.command(val, "WHERE", 30) == {:error, :timeout}
    assert Vws.Test.Eventually.eventually(fn -> VAL.info(val).queued == 0 end)
    assert Process.info(self(), :messages) == {:messages, []}
  end
end
