defmodule Vws.Acceptance.GuaranteesTest do
  # Issue 24's black-box checks, against `mix vws.serve` as the README runs it: a real OS process
  # with its simulated floor, driven over the real WC TCP link by the integrator's command line.
  use ExUnit.Case, async: true

  alias Vws.Test.Acceptance

  @moduletag :acceptance
  @moduletag :tmp_dir
  @moduletag timeout: 240_000

  setup_all do
    Acceptance.prebuild("dev")
  end

  defp serve(extra) do
    wc = Acceptance.free_port()
    http = Acceptance.free_port()

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "#{http}"] ++ extra,
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    %{proc: proc, wc: wc, http: http}
  end

  # `mix vws.serve` with its journal in `dir`, started again after each stop on the same one
  defp serve_journal(dir) do
    wc = Acceptance.free_port()

    proc =
      Acceptance.start(
        ["mix", "vws.serve", "--wc-port", "#{wc}", "--http-port", "0", "--journal", dir],
        env: [{"MIX_ENV", "dev"}]
      )

    on_exit(fn -> Acceptance.stop(proc) end)
    Acceptance.await(proc, ~r/SUN_COMM waits for the WC on tcp:\/\/127\.0\.0\.1:#{wc}/, 90_000)
    %{proc: proc, wc: wc}
  end

  defp pad4(n), do: String.pad_leading(Integer.to_string(n), 4, "0")

  # every status the WC may ask: command statuses and device statuses, each answered in words
  @statuses ~w(ROBOT_CMD MONARCH_CMD GRIPPER_CMD FIXTURE_CMD VACUUM_CMD HYDRAULIC_CMD GRIPPER
               TABLE VISE TRAYS VACUUM TLI_TABLE CHANGER_1 MONARCH WHERE_ROBOT PALLET)

  defp all_statuses(wc, seq) do
    for {name, i} <- Enum.with_index(@statuses), into: %{} do
      s = pad4(seq + i)
      reply = Acceptance.wc_request(wc, "*#{s}*S#{s}#{name}*")
      assert [_, text] = Regex.run(~r/^\d\dS#{s}(.*)\d{3}$/, reply), "#{name}: #{reply}"
      refute text =~ ~r/[{}%]|Elixir|:[a-z]/, "#{name}: #{text}"
      {name, text}
    end
  end

  test "after rule-breaking strings, garbage and a cut-off transfer, it starts again after SIGTERM and kill -9 and answers every status",
       %{tmp_dir: tmp} do
    journal = Path.join(tmp, "journal")
    %{proc: proc, wc: wc} = serve_journal(journal)

    {:ok, sock} = :gen_tcp.connect({127, 0, 0, 1}, wc, [:binary, active: false, packet: :line])
    send_line = fn line -> :ok = :gen_tcp.send(sock, line <> "\r\n") end

    recv = fn ->
      {:ok, line} = :gen_tcp.recv(sock, 0, 10_000)
      String.trim_trailing(line)
    end

    # garbage, a line with a bad BCC, an unknown set letter, rule 1 and rule 2 broken
    send_line.("\x00\xFF garbage \x1B[2J")
    assert recv.() == "E"
    send_line.("*0001*G0001OPEN*999")
    assert recv.() == "E"

    for frame <- [
          "*0002*Q0001JUMP*",
          "*0003*G0001OPEN*G0002CLOSE*",
          "*0004*S0001VISE*R0001WHERE*"
        ] do
      send_line.(Acceptance.wc_frame(frame))
      assert recv.() =~ ~r/^05A#{String.slice(frame, 1, 4)}\d{3}$/
    end

    # a DOWNLOAD_HP cut off after two of its lines: the WC goes away
    send_line.(Acceptance.wc_frame("*0005*M0001DOWNLOAD_HP*"))
    assert recv.() =~ ~r/^05A0005\d{3}$/

    for {n, text} <- [{1, "%"}, {2, "O4711"}] do
      send_line.(Acceptance.wc_frame(pad4(n) <> text))
      assert recv.() =~ ~r/^A#{pad4(n)}\d{3}$/
    end

    :gen_tcp.close(sock)
    before = all_statuses(wc, 10)
    assert before["GRIPPER_CMD"] =~ ~r/^0002ERROR RULE 1/
    assert before["ROBOT_CMD"] =~ ~r/^0001ERROR RULE 2/

    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 30_000) == 0, Acceptance.output(proc)
    %{proc: proc, wc: wc} = serve_journal(journal)
    after_term = all_statuses(wc, 100)

    Acceptance.signal(proc, "KILL")
    assert Acceptance.await_exit(proc, 30_000) in [137, 9]
    %{proc: proc, wc: wc} = serve_journal(journal)
    after_kill = all_statuses(wc, 200)

    # the command statuses read as before the stops; nothing ran twice
    for name <- ~w(ROBOT_CMD MONARCH_CMD GRIPPER_CMD FIXTURE_CMD VACUUM_CMD HYDRAULIC_CMD) do
      assert after_term[name] == before[name], name
      assert after_kill[name] == before[name], name
    end

    # and it takes work
    assert Acceptance.wc_request(wc, "*0300*F0001OPEN*") =~ ~r/^05A0300\d{3}$/

    assert Acceptance.await_command(
             wc,
             "FIXTURE_CMD",
             301,
             1,
             System.monotonic_time(:millisecond) + 30_000
           ) =~
             ~r/0001DONE/

    Acceptance.signal(proc, "TERM")
    assert Acceptance.await_exit(proc, 30_000) == 0
  end

  test "a 1.2 MB program is refused in words and a small DOWNLOAD_GE works after; DOWNLOAD_HP(cccc) with the right CRC is DONE, a wrong one ends ERROR and keeps the NC file",
       %{tmp_dir: tmp} do
    %{wc: port} = serve(["--time-scale", "20"])

    big =
      ["%", "O7777"] ++
        for(i <- 1..54_000, do: "N#{i} G01 X#{rem(i, 997)}.5 F300") ++ ["M30", "%"]

    size = big |> Enum.map(&(byte_size(&1) + 1)) |> Enum.sum()
    assert size > 1_200_000
    File.write!(Path.join(tmp, "007777.nc"), Enum.join(big, "\n") <> "\n")
    File.cp!("priv/sims/programs/001234.nc", Path.join(tmp, "001234.nc"))
    script = Path.join(tmp, "big.vws")

    File.write!(script, """
    TIMEOUT 300
    DOWNLOAD 007777.nc
    """)

    {status, output} = wc(port, ["--script", script], 300_000)
    assert status != 0, output
    assert output =~ "ERROR PROGRAM TOO LARGE #{size} BYTES (LIMIT 999999)", output

    File.write!(script, """
    DOWNLOAD 001234.nc
    M DOWNLOAD_GE
    M COMPARE_GE
    """)

    {status, output} = wc(port, ["--script", script])
    assert status == 0, output

    # DOWNLOAD_HP(cccc) by hand over the WC link: the right CRC, then a wrong one
    program = ["%", "O4321", "N10 G00 X0", "M30", "%"]
    crc = Vws.Codecs.CRC16.compute(Enum.map_join(program, &(&1 <> "\n")))
    right = Vws.Codecs.WC.ProgramCRC.format(crc)
    wrong = Vws.Codecs.WC.ProgramCRC.format(Bitwise.bxor(crc, 0x0100))

    download = fn seq, number, command ->
      {:ok, sock} =
        :gen_tcp.connect({127, 0, 0, 1}, port, [:binary, active: false, packet: :line])

      s = String.pad_leading("#{seq}", 4, "0")
      n = String.pad_leading("#{number}", 4, "0")
      :ok = :gen_tcp.send(sock, Acceptance.wc_frame("*#{s}*M#{n}#{command}*") <> "\r\n")
      {:ok, ack} = :gen_tcp.recv(sock, 0, 10_000)
      assert ack =~ ~r/^05A#{s}/

      answers =
        for {line, i} <- Enum.with_index(program, 1) do
          :ok =
            :gen_tcp.send(
              sock,
              Acceptance.wc_frame(String.pad_leading("#{i}", 4, "0") <> line) <> "\r\n"
            )

          {:ok, answer} = :gen_tcp.recv(sock, 0, 10_000)
          String.trim(answer)
        end

      :gen_tcp.close(sock)

      {answers,
       Acceptance.await_command(
         port,
         "MONARCH_CMD",
         seq + 1,
         number,
         System.monotonic_time(:millisecond) + 30_000
       )}
    end

    {answers, done} = download.(500, 50, "DOWNLOAD_HP(#{right})")
    assert List.last(answers) =~ ~r/^A0005\/#{right}\d{3}$/
    assert done =~ ~r/0050DONE/

    {answers, refused} = download.(600, 60, "DOWNLOAD_HP(#{wrong})")
    assert List.last(answers) =~ ~r/^A0005\/#{right}\d{3}$/
    assert refused =~ ~r/0060ERROR PROGRAM CRC #{right} EXPECTED #{wrong}/

    # the NC file is the right program still: DOWNLOAD_GE sends it, the machine files 004321.PRO
    {0, out} = wc(port, ["--command", "M DOWNLOAD_GE"])
    assert out =~ ~r/DOWNLOAD_GE: DONE/, out
  end

  defp wc(port, args, timeout \\ 120_000) do
    cli =
      Acceptance.start(
        ["mix", "vws.wc", "--endpoint", "tcp://127.0.0.1:#{port}"] ++ args,
        env: [{"MIX_ENV", "dev"}]
      )

    {Acceptance.await_exit(cli, timeout), Acceptance.output(cli)}
  end

  test "DRIP_FEED with the robot inside the machine ends ERROR INTERLOCK and the machine runs nothing",
       %{tmp_dir: tmp} do
    %{wc: port} = serve(["--time-scale", "20"])
    File.cp!("priv/sims/programs/001234.nc", Path.join(tmp, "001234.nc"))

    script = Path.join(tmp, "arm_inside.vws")

    File.write!(script, """
    R DISABLE_TABLE
    R DO APPRO VISE/50
    R DO MOVES VISE
    DOWNLOAD 001234.nc
    M DRIP_FEED
    """)

    {status, output} = wc(port, ["--script", script])
    assert status != 0, output
    assert output =~ "MONARCH command 0002 ended ERROR INTERLOCK TABLE HELD BY ROBOT", output

    # the machine ran nothing: MONARCH idle, and CYCLE_START is refused the same way
    {0, monarch} = wc(port, ["--status", "MONARCH"])
    assert monarch =~ "IDLE", monarch
    {_, cycle} = wc(port, ["--command", "M CYCLE_START"])
    assert cycle =~ ~r/M\d{4} CYCLE_START: ERROR INTERLOCK TABLE HELD BY ROBOT/, cycle
  end
end
