defmodule Vws.OptionsTest do
  use ExUnit.Case, async: true

  alias Vws.Options.Error

  doctest Vws.Options

  defp id, do: "options-#{System.unique_integer([:positive])}"

  describe "SUN_COMM's start options" do
    test "a bad value is refused before anything starts, naming the option" do
      ws = id()

      for {opts, message} <- [
            {[bcc: :crc], "invalid SUN_COMM option :bcc: expected one of [:sum, :xor], got :crc"},
            {[takeover_after: -1],
             "invalid SUN_COMM option :takeover_after: expected a non-negative integer, got -1"},
            {[send_timeout: "5s"],
             "invalid SUN_COMM option :send_timeout: expected a positive integer, got \"5s\""},
            {[allow: "10.0.0.300"], "invalid SUN_COMM option :allow: expected an allow-list"},
            {[wc: "udp://x"], "invalid SUN_COMM option :wc: expected nil or an endpoint"},
            {[baud: 9600], "unknown SUN_COMM option :baud (known: :workstation, :wc, :bcc"}
          ] do
        error =
          assert_raise Error, fn -> Vws.CEC.SunComm.start_link([workstation: ws] ++ opts) end

        assert Exception.message(error) =~ message
        assert error.key == opts |> hd() |> elem(0)
      end

      assert_raise Error, "missing SUN_COMM option :workstation", fn ->
        Vws.CEC.SunComm.start_link(wc: nil)
      end

      assert Vws.CEC.Workstation.whereis(ws, :sun_comm) == nil
    end

    test "validated options come back with every default, the allow-list parsed" do
      assert {:ok, opts} =
               Vws.CEC.SunComm.validate_options(workstation: "W", allow: "10.0.0.0/24")

      assert opts[:bcc] == :sum and opts[:takeover_grace] == 500 and opts[:wc] == nil
      assert opts[:allow] == [{{10, 0, 0, 0}, 24}]
      # checking them again changes nothing
      assert Vws.CEC.SunComm.validate_options(opts) == {:ok, opts}
    end
  end

  describe "the workstation's start options" do
    test "an unknown or bad option, its own or SUN_COMM's, is refused before anything starts" do
      Process.flag(:trap_exit, true)
      ws = id()

      assert_raise Error, ~r/^unknown workstation option :wc_port \(known: :id, :wc/, fn ->
        Vws.CEC.Workstation.start_link(id: ws, wc_port: 7070)
      end

      assert_raise Error,
                   ~r/^invalid workstation option :sun_comm: expected a keyword list/,
                   fn ->
                     Vws.CEC.Workstation.start_link(id: ws, sun_comm: :xor)
                   end

      assert_raise Error, "missing workstation option :id", fn ->
        Vws.CEC.Workstation.start_link(wc: nil)
      end

      error =
        assert_raise Error, fn ->
          Vws.CEC.Workstation.start_link(
            id: ws,
            wc: "loopback:#{ws}",
            sun_comm: [upload_retries: :five]
          )
        end

      assert Exception.message(error) ==
               "invalid SUN_COMM option :upload_retries: expected a non-negative integer, got :five"

      # through the node's workstation supervisor: the same error, and nothing left running
      assert {:error, {%Error{key: :bcc, what: "SUN_COMM"}, _stacktrace}} =
               Vws.CEC.Workstation.start(id: ws, wc: "loopback:#{ws}", sun_comm: [bcc: "xor"])

      assert Vws.CEC.Workstation.whereis(ws) == nil
      refute Vws.CEC.Mailbox.exists?(ws)
    end

    test "good options start it, SUN_COMM with the options given" do
      ws = id()

      {:ok, _} =
        Vws.CEC.Workstation.start(
          id: ws,
          wc: "loopback:#{ws}",
          sun_comm: [bcc: :xor, max_line: 80]
        )

      on_exit(fn -> Vws.CEC.Workstation.stop(ws) end)
      assert Vws.CEC.SunComm.await_listening(ws, 5_000) != nil
      assert {:ok, peer} = Vws.Test.WCPeer.connect("loopback:#{ws}")
      # a line over 80 bytes is refused at once
      Vws.Test.WCPeer.send_line(peer, String.duplicate("x", 100))
      assert Vws.Test.WCPeer.recv_line(peer) == "E"
    end
  end
end
