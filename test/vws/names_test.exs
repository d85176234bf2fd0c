defmodule Vws.NamesTest do
  use ExUnit.Case, async: true

  doctest Vws.Names

  test "whereis/2 and workstations/0 find a running workstation's parts" do
    %{ws: ws} = Vws.Test.Workstation.start()
    assert Vws.Names.whereis(ws) == Vws.CEC.Workstation.whereis(ws)
    assert is_pid(Vws.Names.whereis(ws, :sun_comm))
    assert ws in Vws.Names.workstations()
  end
end
