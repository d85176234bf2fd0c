defmodule Vws.Codecs.WC.StatusTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.{Reply, Status}

  doctest Status

  test "every name is classified as what it asks, whatever its case and blanks" do
    for name <- Status.names() do
      assert {kind, _} = Status.classify(" " <> String.downcase(name) <> " ")
      assert kind in [:command, :device]
    end

    assert Status.classify("VISE_CMD") == Status.classify("FIXTURE_CMD")
    assert Status.classify("S_CMD") == {:unknown, "S_CMD"}
    assert Status.classify("where") == {:unknown, "WHERE"}
    assert Status.unknown_answer("WHERE") == "ERROR UNKNOWN STATUS WHERE"
  end

  test "property: a name asks the same whether or not it is spelt exactly" do
    # the exact names take a short way (no trimming or upcasing): it must agree with the long one
    gen =
      :proper_types.tuple([
        :proper_types.oneof(
          Enum.map(Status.names() ++ ["A_CMD", "Q_CMD", "WHERE"], &{:exactly, &1})
        ),
        :proper_types.oneof(["", " ", "  "]),
        :proper_types.oneof(["", " "]),
        :proper_types.bool()
      ])

    property =
      :proper.forall(gen, fn {{:exactly, name}, before, after_, down} ->
        spelt = before <> if(down, do: String.downcase(name), else: name) <> after_
        Status.classify(spelt) == Status.classify(name)
      end)

    assert_property(property, 300)
  end

  test "device answers: NO DATA before anything was written, else the text" do
    assert Status.device_answer(nil) == "NO DATA"
    assert Status.device_answer("VISE OPEN") == "VISE OPEN"
  end

  test "any answer fits a status reply (94 characters)" do
    gen =
      :proper_types.tuple([
        :proper_types.oneof([:proper_types.range(0, 9999), nil]),
        :proper_types.list(:proper_types.range(?\s, ?~))
      ])

    property =
      :proper.forall(gen, fn {number, chars} ->
        text = List.to_string(chars)

        Enum.all?(
          [
            Status.command_answer(number, {:error, text}),
            Status.command_answer(number, {:no_data, text}),
            Status.device_answer(text),
            Status.unknown_answer(text)
          ],
          &(Reply.validate({:status, 1, &1}) == :ok)
        )
      end)

    assert_property(property, 200)
  end
end
