defmodule Vws.ReleaseUnitTest do
  # The systemd unit shipped in rel/ (issue 30 item 5): the node runs as its own user, hidden
  # from and blind to other users' processes, with no secret on its command line or in the unit.
  use ExUnit.Case, async: true

  @root Path.expand("../..", __DIR__)

  # [{"Key", "value"}] of the [Service] section, in order
  defp service do
    Path.join(@root, "rel/vws.service")
    |> File.read!()
    |> String.split("\n")
    |> Enum.drop_while(&(&1 != "[Service]"))
    |> Enum.drop(1)
    |> Enum.take_while(&(not String.starts_with?(&1, "[")))
    |> Enum.reject(&(&1 == "" or String.starts_with?(&1, "#")))
    |> Enum.map(fn line -> line |> String.split("=", parts: 2) |> List.to_tuple() end)
  end

  defp values(unit, key), do: for({^key, value} <- unit, do: value)

  test "rel/vws.service: its own user, hidden processes, the hardening, restart on failure" do
    unit = service()

    for {key, value} <- [
          {"User", "vws"},
          {"Group", "vws"},
          {"ProtectProc", "invisible"},
          {"NoNewPrivileges", "yes"},
          {"ProtectSystem", "strict"},
          {"ProtectHome", "yes"},
          {"PrivateTmp", "yes"},
          {"Restart", "on-failure"},
          {"CapabilityBoundingSet", ""}
        ] do
      assert values(unit, key) == [value], "#{key}=#{value} expected in rel/vws.service"
    end

    writable = unit |> values("ReadWritePaths") |> Enum.flat_map(&String.split/1)
    assert "/var/lib/vws" in writable and "/var/log/vws" in writable
    assert "RELEASE_TMP=/run/vws" in values(unit, "Environment")
    assert values(unit, "RuntimeDirectory") == ["vws"]

    # no secret in the unit, nor on the command line it starts
    assert values(unit, "ExecStart") == ["/opt/vws/bin/vws start"]

    for {_key, value} <- unit,
        do: refute(value =~ ~r/COOKIE|setcookie|HTTP_TOKEN=|READ_TOKEN=/, value)
  end

  test "rel/vm.args.eex passes no cookie (it would be on the node's command line)" do
    args =
      Path.join(@root, "rel/vm.args.eex")
      |> File.read!()
      |> String.split("\n")
      |> Enum.reject(&String.starts_with?(&1, "#"))

    refute Enum.any?(args, &(&1 =~ "setcookie"))
  end
end
