defmodule Vws.Peers.WC.CLI do
  @moduledoc """
  A workstation controller on the command line, for an integrator driving a live controller
  without writing Elixir: `mix vws.wc …` in a checkout, `bin/vws-wc …` in a release (the same
  options; both call `main/1`). It speaks the WC link as `Vws.Peers.WC.Client` does (BCC, resends on
  `E`, the seed's polling rule) and ends with an exit status.

      mix vws.wc --status ROBOT_CMD                     # one status, printed
      mix vws.wc --command 'F OPEN'                     # one command, polled to its end
      mix vws.wc --script priv/sims/table1.vws          # a cycle script (Vws.Peers.WC.Script)
      mix vws.wc --send '*0001*S0001ROBOT_CMD*'         # one raw string; the BCC is added
      bin/vws-wc --endpoint tcp://10.0.0.5:7070 --command 'R DO MOVE SAFE'

  Options:

    * `--endpoint E` — where SUN_COMM serves the WC (default `tcp://127.0.0.1:7070`, the
      default of `mix vws.serve`; any `Vws.Links.Transport` endpoint, a `tty:` too)
    * `--status NAME` — asks a status (`ROBOT_CMD`, `VISE`, `PALLET`, …) once and prints it
    * `--command 'L TEXT'` — sends command TEXT of set L (`R`, `M`, `G`, `F`, `V`, `H`) and
      asks its status until it ends: `DONE` exits 0, `ERROR <reason>` prints it and exits 1
    * `--script FILE` — runs a cycle script, printing the dialogue and the summary; exits 0
      only if it completed
    * `--send STRING` — sends one WC string as it is (with its BCC added when it ends in `*`)
      and prints the reply line; exits 0 on an acknowledgement (`05A…`) or a status answer
    * `--bcc sum|xor` (default sum), `--timeout MS` (a command's or a script step's, default
      60 000), `--quiet` (print only the result)

  Exit status: 0 success; 1 the controller answered, but not success (`ERROR …`, `E`, a script
  stopped); 2 a usage error, or the controller cannot be reached or does not answer.

  Command numbers continue from what the controller's command statuses show, and the string
  sequence starts at a random number, so that two runs in a row are never taken by SUN_COMM
  for a retransmission of the same string (which it acknowledges without running it again).
  """

  alias Vws.Peers.WC.{Client, Printer, Runner, Script}
  alias Vws.Peers.WC.Runner.Summary

  @switches [
    endpoint: :string,
    status: :string,
    command: :string,
    script: :string,
    send: :string,
    bcc: {:in, ["sum", "xor"]},
    timeout: :pos_integer,
    quiet: :boolean,
    help: :boolean
  ]

  @sets ~w(R M G F V H)

  @doc "Runs the command line `argv`; prints to standard output; returns the exit status."
  @spec main([String.t()]) :: 0 | 1 | 2
  def main(argv) do
    case parse(argv) do
      {:ok, action, opts} ->
        run(action, opts)

      {:error, message} ->
        IO.puts(:stderr, "vws.wc: #{message}\n\n" <> usage())
        2
    end
  end

  @doc false
  # For the release's bin/vws-wc (bin/vws eval takes no arguments: they come as VWS_CLI_ARG_<i>
  # environment variables, VWS_CLI_ARGC of them); halts the VM with the exit status.
  def release_main do
    argc = String.to_integer(System.get_env("VWS_CLI_ARGC", "0"))
    argv = for i <- 0..(argc - 1)//1, do: System.get_env("VWS_CLI_ARG_#{i}", "")
    System.halt(main(argv))
  end

  @doc false
  def usage do
    """
    usage: vws.wc [--endpoint tcp://HOST:PORT] (--status NAME | --command 'L TEXT' |
                  --script FILE | --send STRING) [--bcc sum|xor] [--timeout MS] [--quiet]
    """
  end

  ## Arguments

  defp parse(argv) do
    # the flags' errors in words, as every VWS command says them (Vws.CLIOptions)
    with {:ok, opts, rest} <- Vws.CLIOptions.parse(argv, @switches) do
      actions = Keyword.take(opts, [:status, :command, :script, :send])

      cond do
        opts[:help] -> {:error, "help"}
        rest != [] -> {:error, "#{hd(rest)}: unexpected argument (every option starts with --)"}
        length(actions) != 1 -> {:error, "give one of --status, --command, --script, --send"}
        true -> check_action(hd(actions), opts)
      end
    end
  end

  defp check_action({:command, text} = action, opts) do
    case String.split(text, " ", parts: 2) do
      [letter, command] when letter in @sets and command != "" -> {:ok, action, opts}
      _ -> {:error, "--command takes a set letter (#{Enum.join(@sets, " ")}) and the command"}
    end
  end

  defp check_action(action, opts), do: {:ok, action, opts}

  defp endpoint(opts), do: opts[:endpoint] || "tcp://127.0.0.1:7070"
  defp bcc(opts), do: if(opts[:bcc] == "xor", do: :xor, else: :sum)
  defp timeout(opts), do: opts[:timeout] || 60_000

  defp say(opts, text), do: unless(opts[:quiet], do: IO.puts(text))

  ## Actions

  defp run({:send, string}, opts) do
    line = if String.ends_with?(string, "*"), do: frame(string, bcc(opts)), else: string

    with {:ok, conn} <- Vws.CEC.Cell.connect(endpoint(opts)),
         :ok <- Vws.Links.Transport.activate(conn) do
      try do
        say(opts, "→ #{Printer.printable(line)}")
        :ok = Vws.Links.Transport.send(conn, [line, "\r\n"])

        case receive_line(conn, Vws.Codecs.WC.LineDecoder.new(), min(timeout(opts), 10_000)) do
          {:ok, reply} ->
            IO.puts(if opts[:quiet], do: reply, else: "← #{Printer.printable(reply)}")
            send_status(reply, bcc(opts))

          {:error, reason} ->
            IO.puts("no reply: #{reason}")
            2
        end
      after
        Vws.Links.Transport.close(conn)
      end
    else
      {:error, reason} -> unreachable(opts, reason)
    end
  end

  defp run({:status, name}, opts) do
    with_client(opts, %{}, fn client ->
      case Client.status(client, name) do
        {:ok, text} ->
          IO.puts(text)
          0

        {:error, error} ->
          IO.puts("#{name}: #{Exception.message(error)}")
          2
      end
    end)
  end

  defp run({:command, text}, opts) do
    [letter, command] = String.split(text, " ", parts: 2)

    with {:ok, numbers} <- next_numbers(opts, [letter]) do
      with_client(opts, numbers, fn client ->
        with {:ok, [{^letter, number}]} <- Client.send_commands(client, [{letter, command}]),
             _ = say(opts, "sent #{letter}#{pad(number)}#{command}; waiting for its end"),
             :done <- Client.await_command(client, letter, number, timeout(opts)) do
          IO.puts("#{letter}#{pad(number)} #{command}: DONE")
          0
        else
          {:error, %Vws.Peers.WC.ClientError{reason: :command_failed, data: data}} ->
            IO.puts("#{letter}#{pad(data.number)} #{command}: #{data.status}")
            1

          {:error, error} ->
            IO.puts("#{letter} #{command}: #{Exception.message(error)}")
            if match?(%Vws.Peers.WC.ClientError{reason: :nak}, error), do: 1, else: 2
        end
      end)
    end
  end

  defp run({:script, path}, opts) do
    case Script.parse_file(path) do
      {:ok, script} ->
        with {:ok, numbers} <- next_numbers(opts, @sets) do
          with_client(opts, numbers, &run_script(&1, script, path, opts))
        end

      {:error, error} ->
        IO.puts(:stderr, "vws.wc: #{Exception.message(error)}")
        2
    end
  end

  defp run_script(client, script, path, opts) do
    say(opts, "script #{path} (#{length(script.steps)} steps) against #{endpoint(opts)}")
    :ok = Client.subscribe(client, self())
    task = Task.async(fn -> Runner.run(client, script, timeout: timeout(opts)) end)
    summary = print_until(task, client, Printer.new(), opts)
    Enum.each(Summary.format(summary), &IO.puts(Printer.readable(&1)))
    if Summary.completed?(summary), do: 0, else: 1
  end

  defp print_until(%Task{ref: ref} = task, client, printer, opts) do
    receive do
      {:wc_client, ^client, event} ->
        printer = if opts[:quiet], do: printer, else: Printer.print_event(event, printer)
        print_until(task, client, printer, opts)

      {^ref, summary} ->
        Process.demonitor(ref, [:flush])
        summary
    end
  end

  ## The link

  defp with_client(opts, numbers, fun) do
    sequence = :rand.uniform(9000)

    case Client.connect(endpoint(opts),
           bcc: bcc(opts),
           sequence: sequence,
           numbers: numbers,
           connect_timeout: 5_000
         ) do
      {:ok, client} ->
        try do
          fun.(client)
        after
          Client.close(client)
        end

      {:error, reason} ->
        unreachable(opts, reason)
    end
  end

  # The number after the one each set's command status shows (what a WC that kept counting
  # would send next); 1 for a set that has run nothing.
  defp next_numbers(opts, letters) do
    with_numbers = fn client ->
      Enum.reduce_while(letters, {:ok, %{}}, fn letter, {:ok, acc} ->
        case Client.status(client, Client.command_status_name(letter)) do
          {:ok, text} ->
            last =
              case Client.command_status(text) do
                {:ok, n, _word} -> n
                :error -> 0
              end

            {:cont, {:ok, Map.put(acc, letter, rem(last, 9999) + 1)}}

          {:error, error} ->
            {:halt, {:error, error}}
        end
      end)
    end

    case with_client(opts, %{}, with_numbers) do
      {:ok, numbers} ->
        {:ok, numbers}

      {:error, error} ->
        IO.puts("cannot read the command statuses: #{Exception.message(error)}")
        2

      status when is_integer(status) ->
        status
    end
  end

  defp unreachable(opts, reason) do
    IO.puts("cannot reach the controller at #{endpoint(opts)}: #{reason_text(reason)}")
    2
  end

  defp reason_text(%{__exception__: true} = error), do: Exception.message(error)
  defp reason_text(reason), do: inspect(reason)

  defp receive_line(conn, decoder, timeout) do
    receive do
      message ->
        case Vws.Links.Transport.handle_message(conn, message) do
          {:data, bytes} ->
            case Vws.Codecs.WC.LineDecoder.feed(decoder, bytes) do
              {[line | _], _} when is_binary(line) -> {:ok, line}
              {[{:error, error} | _], _} -> {:error, Exception.message(error)}
              {[], decoder} -> receive_line(conn, decoder, timeout)
            end

          :closed ->
            {:error, "the controller closed the link"}

          {:error, reason} ->
            {:error, reason_text(reason)}

          :unknown ->
            receive_line(conn, decoder, timeout)
        end
    after
      timeout -> {:error, "none in #{timeout} ms"}
    end
  end

  defp send_status(reply, bcc) do
    case Vws.Codecs.WC.Reply.decode(reply, bcc: bcc) do
      {:ok, {:ack, _}} -> 0
      {:ok, {:status, _, _}} -> 0
      {:ok, _} -> 1
      {:error, _} -> 1
    end
  end

  defp frame(data, mode),
    do: data <> Vws.Codecs.WC.BCC.encode(Vws.Codecs.WC.BCC.compute(data, mode))

  defp pad(n), do: String.pad_leading(Integer.to_string(n), 4, "0")
end
