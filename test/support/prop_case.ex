defmodule Vws.PropCase do
  @moduledoc """
  PropEr from ExUnit. `use Vws.PropCase` imports `assert_property/2`, which runs a PropEr property
  quietly and fails the test with PropEr's counterexample when it does not hold.

      property = :proper.forall(:proper_types.binary(), fn bin -> byte_size(bin) >= 0 end)
      assert_property(property, 200)
  """

  defmacro __using__(_opts) do
    quote do
      import Vws.PropCase
    end
  end

  @doc "Runs `property` for `numtests` cases; fails with the shrunk counterexample."
  def assert_property(property, numtests \\ 200) do
    case :proper.quickcheck(property, [:quiet, {:numtests, numtests}, :long_result]) do
      true ->
        true

      other ->
        counterexample = :proper.counterexample()

        ExUnit.Assertions.flunk(
          "property failed: #{inspect(other)}; counterexample: #{inspect(counterexample, limit: :infinity)}"
        )
    end
  end
end
