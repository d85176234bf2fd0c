defmodule Vws.DAQTest do
  use ExUnit.Case, async: true
  doctest Vws.DAQ
  doctest Vws.DAQ.Readings
  doctest Vws.DAQ.DeviceStatus
end
