defmodule Vws.HPIBTest do
  use ExUnit.Case, async: true
  doctest Vws.HPIB
end
