defmodule Vws.CLIOptionsTest do
  use ExUnit.Case, async: true

  alias Vws.CLIOptions

  doctest Vws.CLIOptions
  doctest Vws.Ops.StartError

  @serve [
    wc_port: :port_or_zero,
    http_port: :port_or_zero,
    bcc: {:in, ["sum", "xor"]},
    time_scale: :positive_float,
    ber: :probability,
    seed: :non_neg_integer,
    id: :string,
    once: :boolean
  ]

  test "each wrong flag is one line naming the flag and what is wrong, never an Elixir term" do
    cases = [
      {["--wc-port", "abc"], "--wc-port: abc is not a port number (0-65535; 0 picks a free one)"},
      {["--wc-port", "70000"],
       "--wc-port: 70000 is not a port number (0-65535; 0 picks a free one)"},
      {["--wc-port", "-1"], "--wc-port: -1 is not a port number (0-65535; 0 picks a free one)"},
      {["--http-port", "80x"],
       "--http-port: 80x is not a port number (0-65535; 0 picks a free one)"},
      {["--bcc", "crc"], "--bcc: crc is not one of sum, xor"},
      {["--time-scale", "fast"], "--time-scale: fast is not a number above 0"},
      {["--time-scale", "-2"], "--time-scale: -2 is not a number above 0"},
      {["--ber", "2"], "--ber: 2 is not a number from 0 to 1"},
      {["--seed", "1.5"], "--seed: 1.5 is not a whole number"},
      {["--id"], "--id: needs a value"},
      {["--time-scal", "2"], "--time-scal: unknown option (did you mean --time-scale?)"},
      {["--frobnicate"],
       "--frobnicate: unknown option (known: --wc-port --http-port --bcc --time-scale --ber --seed --id --once)"}
    ]

    for {argv, line} <- cases do
      assert CLIOptions.parse(argv, @serve) == {:error, line}, inspect(argv)
      refute line =~ ~r/[{}\[\]]/
    end
  end

  test "good values come back converted, in order, with the other arguments" do
    assert CLIOptions.parse(
             ~w(--wc-port 7071 --time-scale 20 --ber 1e-4 --bcc xor --once part.nc --id A),
             @serve
           ) ==
             {:ok,
              [wc_port: 7071, time_scale: 20.0, ber: 1.0e-4, bcc: "xor", once: true, id: "A"],
              ["part.nc"]}

    assert CLIOptions.parse(["--wc-port", "0"], @serve) == {:ok, [wc_port: 0], []}
    assert CLIOptions.parse(["--wc-port", "1"], wc_port: :port) == {:ok, [wc_port: 1], []}

    assert CLIOptions.parse(["--wc-port", "0"], wc_port: :port) ==
             {:error, "--wc-port: 0 is not a port number (1-65535)"}
  end

  test "parse! raises Mix.Error with the line, and refutes stray arguments unless asked for" do
    assert_raise Mix.Error, "--wc-port: abc is not a port number (1-65535)", fn ->
      CLIOptions.parse!(["--wc-port", "abc"], wc_port: :port)
    end

    assert_raise Mix.Error, "stray: unexpected argument (every option starts with --)", fn ->
      CLIOptions.parse!(["stray"], wc_port: :port)
    end

    assert CLIOptions.parse!(["f.nc", "--wc-port", "9"], [wc_port: :port], args: true) ==
             {[wc_port: 9], ["f.nc"]}
  end

  test "mix vws.library's flags are answered the same way (status 2, the line on standard error)" do
    import ExUnit.CaptureIO

    err =
      capture_io(:stderr, fn ->
        capture_io(fn ->
          send(self(), {:status, Vws.Ops.LibraryCLI.main(~w(show 1.PRO --version two))})
        end)
      end)

    assert_received {:status, 2}
    assert err =~ "--version: two is not a whole number above 0"
    refute err =~ "unknown options"
  end

  test "a WC port in use and an address not of this host are said in words" do
    {:ok, socket} = :gen_tcp.listen(0, ip: {127, 0, 0, 1}, reuseaddr: false)
    {:ok, port} = :inet.port(socket)
    on_exit(fn -> :gen_tcp.close(socket) end)
    wc = "tcp://127.0.0.1:#{port}"

    assert {:error, reason} = Vws.Application.check_wc_port(wc)
    assert Vws.Ops.StartError.describe(reason) == "WC port #{port} is in use (#{wc})"

    assert {:error, reason} = Vws.Application.check_wc_port("tcp://192.0.2.77:7070")

    assert Vws.Ops.StartError.describe(reason) ==
             "WC address 192.0.2.77 is not an address of this host (tcp://192.0.2.77:7070)"

    assert Vws.Application.check_wc_port("tcp://127.0.0.1:0") == :ok
    assert Vws.Application.check_wc_port("loopback:x") == :ok
  end

  test "a release's VWS_WC that cannot be read or opened: why, in one line, before anything starts" do
    assert Vws.Application.start_checked(id: "CLI-OPT-1", wc: "tcp://127.0.0.1:70000") ==
             {:error,
              ~s(VWS_WC: invalid endpoint "tcp://127.0.0.1:70000": the port must be a number from 0 to 65535)}

    {:ok, socket} = :gen_tcp.listen(0, ip: {127, 0, 0, 1})
    {:ok, port} = :inet.port(socket)
    on_exit(fn -> :gen_tcp.close(socket) end)

    assert Vws.Application.start_checked(id: "CLI-OPT-2", wc: "tcp://127.0.0.1:#{port}") ==
             {:error, "WC port #{port} is in use (tcp://127.0.0.1:#{port})"}

    assert Vws.CEC.Workstation.whereis("CLI-OPT-2") == nil

    assert {:error, line} =
             Vws.Application.start_checked(id: "CLI-OPT-3", wc: "tcp://0.0.0.0:7070")

    assert line =~ ~r/^tcp:\/\/0\.0\.0\.0:7070 is not a loopback address: .*VWS_WC_ALLOW/

    assert Vws.Application.start_checked(
             id: "CLI-OPT-4",
             wc: "tcp://0.0.0.0:7070",
             sun_comm: [allow: "10.0.0.5,nonsense"]
           ) == {:error, ~s(VWS_WC_ALLOW: "nonsense" is not an address or address/prefix)}
  end
end
