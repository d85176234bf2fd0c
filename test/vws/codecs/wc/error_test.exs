defmodule Vws.Codecs.WC.ErrorTest do
  use ExUnit.Case, async: true

  alias Vws.Codecs.WC.Error

  doctest Error

  test "every reason has a plain message" do
    errors = [
      %Error{reason: :bad_bcc, data: %{computed: 1, received: 2}},
      %Error{reason: :malformed, data: String.duplicate("x", 200)},
      %Error{reason: :bad_sequence, data: "054"},
      %Error{reason: :bad_command, data: "r0009X"},
      %Error{reason: :line_too_long, data: %{length: 2000, max_line: 1024}},
      %Error{reason: :text_too_long, data: %{length: 95, max: 94}}
    ]

    for error <- errors do
      message = Exception.message(error)
      assert is_binary(message) and message != ""
      refute message =~ "WC link error"
    end

    assert_raise Error, ~r/sequence number/, fn ->
      raise %Error{reason: :bad_sequence, data: "x"}
    end
  end
end
