defmodule Vws.MixProject do
  use Mix.Project

  def project do
    [
      app: :vws,
      version: "0.1.0",
      elixir: "~> 1.14",
      elixirc_paths: elixirc_paths(Mix.env()),
      start_permanent: Mix.env() == :prod,
      deps: [],
      # PropEr comes from Debian's erlang-proper, not from hex: it is on the code path, not a dep
      xref: [exclude: [:proper, :proper_types, :proper_statem, :proper_gen]],
      releases: [
        vws: [
          include_executables_for: [:unix],
          steps: [:assemble, &drop_cookie/1, &cookie_off_argv/1]
        ]
      ]
    ]
  end

  # The node's cookie is made per installation on first start (rel/env.sh.eex), never shipped:
  # the cookie mix writes into the build output would be the same, world-readable, everywhere.
  defp drop_cookie(release) do
    File.rm!(Path.join([release.path, "releases", "COOKIE"]))
    release
  end

  # The cookie never goes on a command line (issue 30 item 5): Elixir's bin/<name> passes
  # `--cookie "$RELEASE_COOKIE"` to every VM it starts (the node, rpc, remote, eval), which
  # becomes `-setcookie` in /proc/<pid>/cmdline, where any local user reads it, connects and runs
  # code as the service's user. Without it, OTP reads the cookie from `$HOME/.erlang.cookie`
  # (owner-only, or it refuses), and rel/env.sh.eex points HOME at the directory holding the
  # installation's cookie. The script is Elixir's own: what is removed must be found, or the build
  # stops rather than ship a release that shows its cookie.
  defp cookie_off_argv(release) do
    bin = Path.join([release.path, "bin", Atom.to_string(release.name)])
    script = File.read!(bin)

    fallback = ~s|RELEASE_COOKIE="${RELEASE_COOKIE:-"$(cat "$RELEASE_ROOT/releases/COOKIE")"}"\n|
    export = "export RELEASE_COOKIE\n"
    line = ~r/^[ \t]*--cookie "\$RELEASE_COOKIE" \\\n/m
    inline = ~s| --cookie "$RELEASE_COOKIE"|

    unless String.contains?(script, fallback <> export) and script =~ line and
             String.contains?(script, inline),
           do: Mix.raise("#{bin} does not pass the cookie as expected: check cookie_off_argv/1")

    script =
      script
      |> String.replace(fallback <> export, "")
      |> String.replace(line, "")
      |> String.replace(inline, "")

    if script =~ ~r/cookie/i,
      do: Mix.raise("#{bin} still passes a cookie: check cookie_off_argv/1")

    File.write!(bin, script)
    release
  end

  def application do
    [
      extra_applications: [:logger, :runtime_tools, :inets, :crypto],
      mod: {Vws.Application, []}
    ]
  end

  defp elixirc_paths(:test), do: ["lib", "test/support"]
  defp elixirc_paths(_), do: ["lib"]
end
