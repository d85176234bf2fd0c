defmodule Vws.CEC.SunCommPropertyTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Test.{WCPeer, Workstation}

  test "any single corrupted byte in a valid string is answered E and runs nothing" do
    %{ws: ws, wc: wc} = Workstation.start()
    {:ok, peer} = WCPeer.connect(wc)

    gen =
      :proper_types.tuple([
        :proper_types.choose(0, 9999),
        :proper_types.choose(0, 9999),
        :proper_types.elements(["OPEN", "CLOSE", "ROTATE_90", "ROTATE_180"]),
        :proper_types.choose(0, 1_000_000),
        :proper_types.choose(1, 255)
      ])

    property =
      :proper.forall(gen, fn {seq, number, text, where, delta} ->
        line = WCPeer.string(seq, [{"G", number, text}]) |> String.trim_trailing("\r\n")
        pos = rem(where, byte_size(line))
        <<before::binary-size(pos), byte, rest::binary>> = line
        corrupted = rem(byte + delta, 256)

        if corrupted in [?\r, ?\n] do
          # a line terminator splits the string in two: each half is answered E
          true
        else
          WCPeer.send_line(peer, <<before::binary, corrupted, rest::binary>>)
          WCPeer.recv_line(peer) == "E" and Vws.CEC.Mailbox.cmd_in(ws, :gripper) == {nil, nil}
        end
      end)

    assert_property(property, 300)
  end
end
