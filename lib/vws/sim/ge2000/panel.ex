defmodule Vws.Sim.GE2000.Panel do
  @moduledoc """
  The simulated GE-2000's operator panel asking the CEC for a program — a remote request (ours,
  issue 27; docs/dnc-drip-feed.md "Remote request"). The machine's side of the wire: its link
  bids with `ENQ DEL` and sends the `R` command `RCS` + `nnnnnn.PRO` (or `nnnnnn.PRO/v`); the CEC
  becomes master and answers with the program, which `Vws.Sim.GE2000` files as `nnnnnn.PRO`
  (whole, ending with its `%` line, as any part program), or with a message block
  `(MSG,REQUEST REFUSED …)`, which it shows to the operator (`state/1`'s `messages`) with alarm 9.
  While the request is under way the simulator answers no R command of the CEC's: those wait
  until the answer is filed, as a control files a program before it answers the next bid.
  """

  alias Vws.Links.DNC
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
      {:ok, link} = GenServer.call(sim, {:program_request, command})

      answer =
        try do
          Vws.Sim.GE2000.connected(
            link,
            System.monotonic_time(:millisecond) + min(timeout, 5_000)
          )

          case DNC.request(link, command, [], timeout) do
            {:ok, blocks} -> {:ok, IO.iodata_to_binary(blocks)}
            error -> error
          end
        catch
          :exit, reason -> {:error, reason}
        end

      # (told in every case: the CEC's R commands wait for it)
      GenServer.call(sim, {:requested_program, file, answer})
    end
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
