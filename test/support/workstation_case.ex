defmodule Vws.Test.Workstation do
  @moduledoc "Starts a workstation for a test, with a unique id and a loopback WC endpoint."

  import ExUnit.Callbacks

  @doc """
  Starts a workstation under the test supervisor. `opts` are `Vws.CEC.Workstation` options; the id
  and the WC endpoint default to unique ones. Returns `%{ws: id, wc: endpoint}`.
  """
  def start(opts \\ []) do
    id = Keyword.get_lazy(opts, :id, fn -> "test-#{System.unique_integer([:positive])}" end)
    wc = Keyword.get(opts, :wc, "loopback:wc-#{id}")
    opts = opts |> Keyword.put(:id, id) |> Keyword.put(:wc, wc)
    pid = start_supervised!({Vws.CEC.Workstation, opts})
    %{ws: id, wc: wc, sup: pid}
  end

  @doc "Robot partition options that hold every command until the test releases it."
  def held_robot(test_pid \\ self()) do
    [
      robot: [
        module: Vws.Test.HeldPartition,
        interlocks: :off,
        link: :test,
        options: [test: test_pid]
      ]
    ]
  end
end
