defmodule Vws.Test.MonarchWC do
  @moduledoc """
  A workstation with a simulated GE-2000 (over its DNC wire protocol) and a program library in
  a directory of its own, driven by a raw WC peer: the program library's and the transfer
  history's end-to-end tests (WC → SUN_COMM → MONARCH → DNC link → `Vws.Sim.GE2000`).
  """

  import ExUnit.Assertions
  import ExUnit.Callbacks
  import Vws.Test.Eventually

  alias Vws.Sim.GE2000
  alias Vws.Test.WCPeer

  @link_opts [reply_timeout: 300, wack_delay: 50, backoff_min: 10, backoff_max: 50]

  @doc """
  Starts it all (under the test's supervisor): `%{ws, peer, sim, dir}`. Options: `:sim`, more
  options of the simulated GE-2000 (`memory:`, `feed_rate:`, …); `:partitions`, the
  workstation's (`Vws.Test.Workstation.start/1`).
  """
  def start(prefix, opts \\ []) do
    dir = Path.join(System.tmp_dir!(), "#{prefix}-#{System.unique_integer([:positive])}")
    on_exit(fn -> File.rm_rf!(dir) end)

    sim =
      start_supervised!(
        {GE2000, [link: @link_opts, cycle_time: 60_000] ++ Keyword.get(opts, :sim, [])}
      )

    %{ws: ws, wc: wc} =
      Vws.Test.Workstation.start(
        [
          devices: [ge2000: [endpoint: GE2000.endpoint(sim), status_interval: nil] ++ @link_opts],
          library: dir
        ] ++ Keyword.take(opts, [:partitions])
      )

    link = Vws.CEC.Workstation.whereis(ws, :ge2000)
    assert eventually(fn -> Vws.Links.DNC.info(link).state == :idle end)
    {:ok, peer} = WCPeer.connect(wc)
    %{ws: ws, peer: peer, sim: sim, dir: dir}
  end

  @doc "A sequence number for a string."
  def seq, do: rem(System.unique_integer([:positive]), 10_000)

  @doc "Sends Monarch command `number` `text` in a string of its own: the string's number, acknowledged."
  def send_monarch(peer, number, text) do
    s = seq()
    WCPeer.send_string(peer, s, [{"M", number, text}])
    assert Vws.Codecs.WC.Reply.decode(WCPeer.recv_line(peer)) == {:ok, {:ack, s}}
    s
  end

  @doc "The Monarch command's status once it has ended, without its number."
  def finished(peer) do
    <<_number::binary-4, status::binary>> =
      WCPeer.await_status(peer, seq(), "MONARCH_CMD", &(not (&1 =~ "EXECUTING")), 30_000)

    status
  end

  @doc "DOWNLOAD_HP of `lines` as the WC sends it, line by line: the command's status."
  def download_hp(peer, number, lines) do
    s = seq()
    WCPeer.send_string(peer, s, [{"M", number, "DOWNLOAD_HP"}])
    assert Vws.Codecs.WC.Reply.decode(WCPeer.recv_line(peer)) == {:ok, {:ack, s}}

    for {line, n} <- Enum.with_index(lines, 1) do
      WCPeer.send_raw(peer, Vws.Codecs.WC.Reply.encode({:line, n, line}))

      assert Vws.Codecs.WC.Reply.decode(WCPeer.recv_line(peer)) ==
               {:ok, WCPeer.download_answer(lines, n)}
    end

    finished(peer)
  end

  @doc """
  A long part program, `O<number>`: `%`, the O word, 88,236 blocks of 17 bytes, `M30`, `%` —
  1,500,024 bytes, more than the 999,999 the GE-2000 stores, well within what the library keeps.
  """
  def long_program(number \\ 88) do
    body = for i <- 1..88_236, do: "N#{rem(i, 9000) + 1000} G01 X#{rem(i, 900) + 100}.5\n"
    IO.iodata_to_binary(["%\nO#{number}\n", body, "M30\n%\n"])
  end
end
