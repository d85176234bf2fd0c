defmodule Vws.Links.EndpointTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.Endpoint
  alias Vws.Links.Endpoint.Error

  doctest Vws.Links.Endpoint
  doctest Vws.Links.Endpoint.Error

  @tty_defaults [baud: 9600, data_bits: 8, parity: :none, stop_bits: 1, flow: :none]

  describe "golden cases" do
    test "tcp with a host name, an IPv4 address, and port 0 for an ephemeral listener" do
      assert Endpoint.parse("tcp://vmc-1.amrf.nbs.gov:5001") ==
               {:ok, %Endpoint{kind: :tcp, host: ~c"vmc-1.amrf.nbs.gov", port: 5001}}

      assert Endpoint.parse("tcp://127.0.0.1:65535") ==
               {:ok, %Endpoint{kind: :tcp, host: ~c"127.0.0.1", port: 65535}}

      assert Endpoint.parse("tcp://localhost:0") ==
               {:ok, %Endpoint{kind: :tcp, host: ~c"localhost", port: 0}}
    end

    test "tty with defaults, with every setting, and as a bare path" do
      assert Endpoint.parse("tty:/dev/ttyS0") ==
               {:ok, %Endpoint{kind: :tty, path: "/dev/ttyS0", serial: @tty_defaults}}

      assert Endpoint.parse("tty:/dev/ttyS0?") ==
               {:ok, %Endpoint{kind: :tty, path: "/dev/ttyS0", serial: @tty_defaults}}

      assert Endpoint.parse("tty:/dev/ttyUSB1?stop_bits=2&parity=odd&data_bits=7&baud=4800") ==
               {:ok,
                %Endpoint{
                  kind: :tty,
                  path: "/dev/ttyUSB1",
                  serial: [baud: 4800, data_bits: 7, parity: :odd, stop_bits: 2, flow: :none]
                }}

      assert Endpoint.parse("/dev/serial/by-id/usb-FTDI_FT232R-if00-port0?baud=115200") ==
               {:ok,
                %Endpoint{
                  kind: :tty,
                  path: "/dev/serial/by-id/usb-FTDI_FT232R-if00-port0",
                  serial: Keyword.put(@tty_defaults, :baud, 115_200)
                }}
    end

    test "flow control, and the same settings on an RFC 2217 terminal server" do
      assert {:ok, %Endpoint{serial: serial}} = Endpoint.parse("tty:/dev/ttyS0?flow=xonxoff")
      assert serial[:flow] == :xonxoff
      assert {:ok, %Endpoint{serial: serial}} = Endpoint.parse("/dev/ttyS0?flow=rtscts")
      assert serial[:flow] == :rtscts

      assert Endpoint.parse("rfc2217://ts-1:2001?baud=4800&parity=even&flow=xonxoff") ==
               {:ok,
                %Endpoint{
                  kind: :rfc2217,
                  host: ~c"ts-1",
                  port: 2001,
                  serial: [baud: 4800, data_bits: 8, parity: :even, stop_bits: 1, flow: :xonxoff]
                }}

      assert Endpoint.parse("rfc2217://127.0.0.1:7000") ==
               {:ok,
                %Endpoint{kind: :rfc2217, host: ~c"127.0.0.1", port: 7000, serial: @tty_defaults}}

      assert to_string(Endpoint.parse!("tty:/dev/x?flow=rtscts")) ==
               "tty:/dev/x?baud=9600&data_bits=8&parity=none&stop_bits=1&flow=rtscts"

      assert to_string(Endpoint.parse!("rfc2217://h:1?parity=odd")) ==
               "rfc2217://h:1?baud=9600&data_bits=8&parity=odd&stop_bits=1"
    end

    test "serial settings where they cannot apply, and unknown ones, are said in words" do
      {:error, e} = Endpoint.parse("tcp://ts-1:2001?baud=4800")
      assert e.reason == :serial_on_tcp
      assert Exception.message(e) =~ "cannot set a serial port: use rfc2217://"

      {:error, e} = Endpoint.parse("tty:/dev/ttyS0?flow=dtrdsr")
      assert e.reason == :bad_flow
      assert Exception.message(e) =~ ~s|flow must be none, xonxoff or rtscts (got "dtrdsr")|

      {:error, e} = Endpoint.parse("rfc2217://h:2001?handshake=xon")
      assert e.reason == :unknown_option

      assert Exception.message(e) =~
               ~s|the serial settings are baud, data_bits, parity, stop_bits and flow (got "handshake")|

      assert {:error, %Error{reason: :bad_port}} = Endpoint.parse("rfc2217://h:0")
      assert {:error, %Error{reason: :missing_port}} = Endpoint.parse("rfc2217://h")
      assert {:error, %Error{reason: :bad_baud}} = Endpoint.parse("rfc2217://h:1?baud=4801")
    end

    test "loopback" do
      assert Endpoint.parse("loopback:dnc") == {:ok, %Endpoint{kind: :loopback, name: "dnc"}}

      assert Endpoint.parse("loopback:ws1/val-ii") ==
               {:ok, %Endpoint{kind: :loopback, name: "ws1/val-ii"}}
    end

    test "canonical strings" do
      assert to_string(Endpoint.parse!("tcp://10.0.0.7:23")) == "tcp://10.0.0.7:23"
      assert to_string(Endpoint.parse!("loopback:hpib")) == "loopback:hpib"

      assert to_string(Endpoint.parse!("tty:/dev/ttyS2?parity=even")) ==
               "tty:/dev/ttyS2?baud=9600&data_bits=8&parity=even&stop_bits=1"

      assert "#{%Endpoint{kind: :loopback, name: {:ws, 1}}}" == "loopback:{:ws, 1}"
    end

    test "bad input gives the reason" do
      for {input, reason} <- [
            {"", :unknown_scheme},
            {"udp://h:1", :unknown_scheme},
            {"TCP://h:1", :unknown_scheme},
            {"ttyS0", :unknown_scheme},
            {"tcp://h", :missing_port},
            {"tcp://:80", :bad_host},
            {"tcp://[::1]:80", :bad_host},
            {"tcp://::1:80", :bad_host},
            {"tcp://256.1.1.1:80", :bad_host},
            {"tcp://1.2.3:80", :bad_host},
            {"tcp://01.2.3.4:80", :bad_host},
            {"tcp://-vmc:80", :bad_host},
            {"tcp://vmc-:80", :bad_host},
            {"tcp://a..b:80", :bad_host},
            {"tcp://a b:80", :bad_host},
            {"tcp://h:", :bad_port},
            {"tcp://h:65536", :bad_port},
            {"tcp://h:-1", :bad_port},
            {"tcp://h:80/", :bad_port},
            {"tcp://h:123456", :bad_port},
            {"tty:", :bad_path},
            {"tty:dev/ttyS0", :bad_path},
            {"tty:/dev/tty S0", :bad_path},
            {"tty:/dev/a,b", :bad_path},
            {"tty:/dev/a:b", :bad_path},
            {"tty:/dev/ttyS0?baud", :bad_option},
            {"tty:/dev/ttyS0?baud=9600&", :bad_option},
            {"tty:/dev/ttyS0?speed=9600", :unknown_option},
            {"tty:/dev/ttyS0?baud=9600&baud=4800", :duplicate_option},
            {"tty:/dev/ttyS0?baud=9601", :bad_baud},
            {"tty:/dev/ttyS0?baud=fast", :bad_baud},
            {"tty:/dev/ttyS0?baud=", :bad_baud},
            {"tty:/dev/ttyS0?data_bits=9", :bad_data_bits},
            {"tty:/dev/ttyS0?parity=mark", :bad_parity},
            {"tty:/dev/ttyS0?parity=NONE", :bad_parity},
            {"tty:/dev/ttyS0?stop_bits=1.5", :bad_stop_bits},
            {"loopback:", :bad_name},
            {"loopback:a b", :bad_name},
            {"loopback:a\nb", :bad_name},
            {"loopback:" <> String.duplicate("x", 256), :bad_name}
          ] do
        assert {:error, %Error{reason: ^reason, input: ^input} = error} = Endpoint.parse(input),
               "#{inspect(input)} should fail with #{reason}"

        assert Exception.message(error) =~ "invalid endpoint"
      end
    end

    test "non-strings are refused, parse! raises" do
      assert {:error, %Error{reason: :not_a_string}} = Endpoint.parse(~c"tcp://h:1")
      assert {:error, %Error{reason: :not_a_string}} = Endpoint.parse(nil)

      assert_raise Error, ~r/the port must be a number from 0 to 65535/, fn ->
        Endpoint.parse!("tcp://h:99999")
      end
    end
  end

  describe "properties" do
    test "parse(to_string(e)) == {:ok, e}" do
      property =
        :proper.forall(endpoint_gen(), fn endpoint ->
          Endpoint.parse(Endpoint.to_string(endpoint)) == {:ok, endpoint}
        end)

      assert_property(property, 500)
    end

    test "garbage never crashes, and whatever parses is canonical" do
      prefixes =
        ["", "tcp://", "tty:", "tty:/dev/", "loopback:", "/", "tcp://h:", "tty:/x?"] ++
          ["rfc2217://", "rfc2217://h:1?", "tty:/x?flow="]

      garbage =
        :proper_types.bind(
          :proper_types.tuple([
            :proper_types.elements(prefixes),
            :proper_types.oneof([
              :proper_types.binary(),
              :proper_types.list(:proper_types.elements(~c"az09.:/?&=,-_ \t%")) |> to_bin()
            ])
          ]),
          fn {prefix, rest} -> prefix <> rest end,
          false
        )

      property =
        :proper.forall(garbage, fn input ->
          case Endpoint.parse(input) do
            {:ok, %Endpoint{} = endpoint} ->
              Endpoint.parse(Endpoint.to_string(endpoint)) == {:ok, endpoint}

            {:error, %Error{} = error} ->
              is_binary(Exception.message(error))
          end
        end)

      assert_property(property, 1000)
    end
  end

  ## Generators

  defp to_bin(list_gen), do: :proper_types.bind(list_gen, &List.to_string/1, false)

  defp chars(list), do: :proper_types.elements(list)

  defp endpoint_gen do
    :proper_types.oneof([tcp_gen(), tty_gen(), rfc2217_gen(), loopback_gen()])
  end

  defp tcp_gen do
    host =
      :proper_types.oneof([
        :proper_types.bind(
          :proper_types.vector(4, :proper_types.integer(0, 255)),
          &Enum.join(&1, "."),
          false
        ),
        :proper_types.bind(
          :proper_types.non_empty(:proper_types.list(label_gen())),
          &(&1 |> Enum.take(3) |> Enum.join(".")),
          false
        )
      ])

    :proper_types.bind(
      :proper_types.tuple([host, :proper_types.integer(0, 65535)]),
      fn {host, port} -> %Endpoint{kind: :tcp, host: String.to_charlist(host), port: port} end,
      false
    )
  end

  defp label_gen do
    alnum = Enum.concat([?a..?z, ?A..?Z, ?0..?9])

    :proper_types.bind(
      :proper_types.tuple([
        chars(Enum.concat(?a..?z, ?A..?Z)),
        :proper_types.list(chars([?- | alnum])),
        chars(alnum)
      ]),
      fn {first, middle, last} ->
        List.to_string([first | Enum.take(middle, 61)] ++ [last])
      end,
      false
    )
  end

  defp tty_gen do
    segment =
      :proper_types.non_empty(
        :proper_types.list(chars(Enum.concat([?a..?z, ?A..?Z, ?0..?9, ~c"._-+@"])))
      )
      |> to_bin()

    :proper_types.bind(
      :proper_types.tuple([
        :proper_types.non_empty(:proper_types.list(segment)),
        :proper_types.elements(Endpoint.bauds()),
        :proper_types.integer(5, 8),
        :proper_types.elements([:none, :even, :odd]),
        :proper_types.integer(1, 2),
        :proper_types.elements([:none, :xonxoff, :rtscts])
      ]),
      fn {segments, baud, data_bits, parity, stop_bits, flow} ->
        %Endpoint{
          kind: :tty,
          path: "/" <> Enum.join(segments, "/"),
          serial: [
            baud: baud,
            data_bits: data_bits,
            parity: parity,
            stop_bits: stop_bits,
            flow: flow
          ]
        }
      end,
      false
    )
  end

  # a terminal server's port: a tcp address (port 1 and up) with a tty's settings
  defp rfc2217_gen do
    :proper_types.bind(
      :proper_types.tuple([tcp_gen(), tty_gen()]),
      fn {tcp, tty} ->
        %Endpoint{kind: :rfc2217, host: tcp.host, port: max(tcp.port, 1), serial: tty.serial}
      end,
      false
    )
  end

  defp loopback_gen do
    printable = Enum.concat([?!..?~, [?é, ?Ω, ?→]])

    :proper_types.bind(
      :proper_types.non_empty(:proper_types.list(chars(printable))),
      fn chars ->
        %Endpoint{kind: :loopback, name: chars |> Enum.take(80) |> List.to_string()}
      end,
      false
    )
  end
end
