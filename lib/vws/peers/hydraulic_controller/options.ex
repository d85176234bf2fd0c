defmodule Vws.Peers.HydraulicController.Options do
  @moduledoc false
  # The seed's task manager `Options` (§5.1) for one CEC connection: a continuous loop that
  # reads the next command line, parses it (`Vws.Codecs.SCPI`) and calls what carries it out. Lines are
  # answered in the order they come (a query's answer is the next line the CEC reads):
  #
  #   CLAMP_PALLET / RELEASE_PALLET  the program starts the sequence (no answer line)
  #   STATUS?                        the program's status, at once, even while a sequence runs
  #   PALLET?                        DAQ #2 read now (this connection waits, no other)
  #   *IDN?, *RST, *CLS, SYST:ERR?   as an instrument: identity, no-ops, this connection's errors
  #
  # A line it cannot parse, or a DAQ command, is not answered: an SCPI error goes on this
  # connection's error queue (at most 20) for SYST:ERR?, as an instrument does.
  require Logger

  alias Vws.Codecs.SCPI
  alias Vws.Links.Transport
  alias Vws.Peers.HydraulicController.Pallet

  @max_errors 20
  @undefined_header {-113, "Undefined header"}

  @doc false
  # Spawns the loop linked to the program; it waits for `:go`, sent once it owns `conn`.
  def start_link(conn, program) do
    spawn_link(fn ->
      receive do
        :go -> :ok
      end

      pallet = GenServer.call(program, :pallet)
      :ok = Transport.activate(conn)
      loop(%{conn: conn, program: program, pallet: pallet, decoder: SCPI.new(), errors: []})
    end)
  end

  defp loop(s) do
    receive do
      msg ->
        case Transport.handle_message(s.conn, msg) do
          {:data, bytes} ->
            {lines, decoder} = SCPI.feed(s.decoder, bytes)
            s = Enum.reduce(lines, %{s | decoder: decoder}, &line/2)
            :ok = Transport.activate(s.conn)
            loop(s)

          :unknown ->
            loop(s)

          _closed_or_error ->
            Transport.close(s.conn)
            exit(:normal)
        end
    end
  end

  defp line({:error, error}, s), do: push_error(s, SCPI.Error.scpi_error(error))

  defp line(text, s) do
    case SCPI.decode_command(text) do
      {:ok, command} -> command(command, s)
      {:error, error} -> push_error(s, SCPI.Error.scpi_error(error))
    end
  end

  defp command(command, s) when command in [:clamp_pallet, :release_pallet] do
    # refused only while another sequence runs; the program logs and counts it
    _ = GenServer.call(s.program, {:run, command})
    s
  end

  defp command(:status?, s), do: answer(s, GenServer.call(s.program, :status))

  defp command(:pallet?, s) do
    case Pallet.read(s.pallet) do
      {:ok, pallet} ->
        Vws.LogLimit.clear(:pallet, "hydraulic controller: PALLET? reads DAQ #2 again")
        answer(s, pallet)

      {:error, why} ->
        # once while DAQ #2 cannot be read, not at every PALLET? the CEC asks
        Vws.LogLimit.warning(:pallet, "hydraulic controller: PALLET? cannot read DAQ #2: #{why}")
        answer(s, Pallet.unknown())
    end
  end

  defp command(:idn?, s) do
    answer(s, %{
      manufacturer: "NBS-VWS",
      model: "HP-9836 HYDRAULIC CONTROLLER",
      serial: "0",
      firmware: "1.0"
    })
  end

  defp command(:syst_err?, s) do
    case s.errors do
      [] -> answer(s, {0, "No error"})
      [oldest | rest] -> answer(%{s | errors: rest}, oldest)
    end
  end

  defp command(command, s) when command in [:rst, :cls], do: %{s | errors: []}
  defp command(_daq_command, s), do: push_error(s, @undefined_header)

  defp answer(s, response) do
    _ = Transport.send(s.conn, SCPI.encode_response(response))
    s
  end

  defp push_error(s, entry) do
    errors =
      if length(s.errors) >= @max_errors,
        do: List.replace_at(s.errors, -1, {-350, "Queue overflow"}),
        else: s.errors ++ [entry]

    %{s | errors: errors}
  end
end
