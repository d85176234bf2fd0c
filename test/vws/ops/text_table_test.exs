defmodule Vws.Ops.TextTableTest do
  use ExUnit.Case, async: true

  alias Vws.Ops.TextTable

  doctest TextTable

  test "columns as wide as their widest cell, header included; no trailing spaces" do
    text = TextTable.render(["A", "LONG HEADER", "C"], [["xxxx", "y", ""], ["z", "", "w"]])

    assert String.split(text, "\n") == [
             "A     LONG HEADER  C",
             "xxxx  y",
             "z" <> String.duplicate(" ", 3 + 2 + 11 + 2) <> "w"
           ]
  end

  test "a header alone" do
    assert TextTable.render(["ID", "NODE"], []) == "ID  NODE"
  end
end
