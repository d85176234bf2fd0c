defmodule Vws.Sim.DAQTest do
  use ExUnit.Case, async: true
  doctest Vws.Sim.DAQ
end
