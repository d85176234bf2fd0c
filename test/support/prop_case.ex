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

  @doc """
  Runs `fun` (a property's body) and returns what it returns; an exception it raises makes the
  case fail (false) and is kept (an exit or throw too) to be shown with the counterexample. (PropEr from Debian reports
  an exception in a property with `erlang:get_stacktrace/0`, gone since OTP 23: without this the
  test shows only that UndefinedFunctionError.)
  """
  def checked(fun) do
    fun.()
  catch
    kind, reason ->
      Process.put({__MODULE__, :raised}, Exception.format(kind, reason, __STACKTRACE__))
      false
  end

  @doc "Runs `property` for `numtests` cases; fails with the shrunk counterexample."
  def assert_property(property, numtests \\ 200) do
    case :proper.quickcheck(property, [:quiet, {:numtests, numtests}, :long_result]) do
      true ->
        true

      other ->
        counterexample = :proper.counterexample()

        raised =
          case Process.delete({__MODULE__, :raised}) do
            nil -> ""
            text -> "\nthe last case that raised:\n" <> text
          end

        ExUnit.Assertions.flunk(
          "property failed: #{inspect(other)}; counterexample: #{inspect(counterexample, limit: :infinity)}" <>
            raised
        )
    end
  end
end
