defmodule Vws.Sim.GE2000.Panel do
  @moduledoc """
  The simulated GE-2000's operator panel asking the CEC for a program — a remote request (ours,
  issue 27; docs/dnc-drip-feed.md "Remote request"). The machine's side of the wire: its link
  bids with `ENQ DEL` and sends the `R` command `RCS` + `nnnnnn.PRO` (or `nnnnnn.PRO/v`); the CEC
  becomes master and answers with the program, which `Vws.Sim.GE2000` files as `nnnnnn.PRO`
  (whole, ending with its `%` line, as any part program), or with a message block
  `(MSG,REQUEST REFUSED …)`, which it shows to the operator (`state/1`'s `messages`) with alarm 9.
  The simulator makes the request itself and files the answer as its reply arrives — before
  anything its link receives after it — so an R command of the CEC's that follows the answer
  (the check after it) finds the program filed, and one that came first is answered at once, as
  the half-duplex line needs: the machine's own R command can go only after it.
  """

  alias Vws.Links.DNC.Frame.Command

  @doc """
  Asks for program `number` (an integer, `"100"`, `"000100"` or `"000100.PRO"`), its latest
  released version or `version`. Returns when the answer is filed or shown: `:ok` (filed),
  `{:error, {:refused, words}}`, `{:error, {:alarm, n}}` (not filed: the machine's alarm),
  `{:error, :bad_name}` (nothing sent) or the link's error. From iex under `mix vws.serve`:
  `Vws.Sim.GE2000.Panel.request_program(Vws.Sim.Floor.ge2000("ws1"), 100)` (the workstation's id).
  """
  @spec request_program(GenServer.server(), integer | String.t(), pos_integer | nil, timeout) ::
          :ok | {:error, term}
  def request_program(sim, number, version \\ nil, timeout \\ 60_000) do
    with {:ok, file} <- file(number),
         :ok <-
           if(version == nil or (is_integer(version) and version > 0),
             do: :ok,
             else: {:error, :bad_name}
           ) do
      text = if version, do: "#{file}/#{version}", else: file
      command = %Command{direction: :receive, check: :crc, operation: :part_program, text: text}
      link = Vws.Sim.GE2000.link(sim)
      Vws.Sim.GE2000.connected(link, System.monotonic_time(:millisecond) + min(timeout, 5_000))
      # the link ends the request by its deadline: the call waits a little longer than that
      wait = if timeout == :infinity, do: :infinity, else: timeout + 5_000
      GenServer.call(sim, {:program_request, command, timeout}, wait)
    end
  catch
    :exit, reason -> {:error, reason}
  end

  # what the operator keys in: 100, "100", "000100" or "000100.PRO"
  defp file(n) when is_integer(n) and n in 0..999_999, do: file(Integer.to_string(n))

  defp file(n) when is_binary(n) do
    cond do
      n =~ ~r/^\d{1,6}$/ -> {:ok, String.pad_leading(n, 6, "0") <> ".PRO"}
      n =~ ~r/^\d{6}\.PRO$/ -> {:ok, n}
      true -> {:error, :bad_name}
    end
  end

  defp file(_n), do: {:error, :bad_name}
end
