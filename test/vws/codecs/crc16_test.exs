defmodule Vws.Codecs.CRC16Test do
  use ExUnit.Case, async: true
  doctest Vws.Codecs.CRC16

  test "the DDCMP STRT vector of PROTOCOLS.md checks to zero with its CRC" do
    assert Vws.Codecs.CRC16.compute(<<0x05, 0x06, 0xC0, 0x00, 0x00, 0x01>>) == 0x9575
    assert Vws.Codecs.CRC16.compute(<<0x05, 0x06, 0xC0, 0x00, 0x00, 0x01, 0x75, 0x95>>) == 0
  end
end
