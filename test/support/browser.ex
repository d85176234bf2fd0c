defmodule Vws.Test.Browser do
  @moduledoc """
  Headless Chromium for the tests that read the dashboard as a person sees it: the page runs for
  a budget of virtual time (its JavaScript polls `/api/state`), then Chromium dumps the DOM it
  ended with, or takes a screenshot. Each run has a profile directory of its own, removed after.
  """

  @doc "The Chromium executable, or nil when none is installed."
  def chromium,
    do: System.find_executable("chromium") || System.find_executable("chromium-browser")

  @doc """
  Runs Chromium headless for `budget_ms` of page time with `extra` arguments after the common
  ones (`["--dump-dom", url]`, `["--screenshot=…", url]`); its standard output. `opts` go to
  `System.cmd/3` (`cd:`).
  """
  def run(budget_ms, extra, opts \\ []) do
    profile = Path.join(System.tmp_dir!(), "vws-chromium-#{System.unique_integer([:positive])}")

    args = headless(profile) ++ ["--virtual-time-budget=#{budget_ms}" | extra]

    try do
      # Chromium's own complaints (no D-Bus in a container) go to /dev/null, its output to us
      {out, 0} = System.cmd("sh", ["-c", ~s(exec "$0" "$@" 2>/dev/null), chromium() | args], opts)
      out
    after
      File.rm_rf(profile)
    end
  end

  @doc "The arguments every headless Chromium of the tests starts with, its profile in `profile`."
  def headless(profile) do
    [
      "--headless=new",
      "--disable-gpu",
      "--no-sandbox",
      "--no-first-run",
      "--disable-extensions",
      "--user-data-dir=" <> profile
    ]
  end

  @doc "The DOM Chromium ends with after `budget_ms` of page time on `url`."
  def dump_dom(url, budget_ms), do: run(budget_ms, ["--dump-dom", url])

  # A page has drawn: loaded; the dashboard polled the node at least `updates` times (its
  # `updates` counter); a command sent from the link's fragment (`#token=…&text=…`) answered.
  defp drawn(updates) do
    """
    (document.readyState === 'complete' &&
     (!document.getElementById('updates') || +document.getElementById('updates').textContent >= #{updates}) &&
     (!/[#&]text=/.test(location.hash) || !!document.getElementById('command-status')))
    """
  end

  @doc """
  The DOM of `url` once the page has drawn (loaded; the dashboard's first poll of the node drawn;
  a command sent from the link's fragment answered), read from the test run's one Chromium
  (`Vws.Test.Browser.CDP`): a fresh tab, so what it shows was fetched after the call. Options:
  `:updates` (the dashboard's polls drawn, 1: its trends need a few), `:until` (a JavaScript
  expression to wait for instead), `:timeout` (ms, 30 000).
  """
  def page(url, opts \\ []) do
    Vws.Test.Browser.CDP.read(url, until(opts), Keyword.get(opts, :timeout, 30_000), :dom)
  end

  @doc "A PNG of the whole page `url` at `width` × `height` once it has drawn (`page/2`), at `path`."
  def screenshot(url, path, {width, height}, opts \\ []) do
    png =
      Vws.Test.Browser.CDP.read(
        url,
        until(opts),
        Keyword.get(opts, :timeout, 30_000),
        {:screenshot, width, height}
      )

    File.write!(path, png)
  end

  defp until(opts),
    do: Keyword.get_lazy(opts, :until, fn -> drawn(Keyword.get(opts, :updates, 1)) end)

  @doc "The visible text of a DOM, roughly as a person reads it (a line per block element)."
  def text(dom) do
    dom
    |> String.replace(~r{<script.*?</script>}s, "")
    |> String.replace(~r{<style.*?</style>}s, "")
    |> String.replace(~r{<(td|th|div|h2|h3|p|tr|span)[^>]*>}, " ")
    |> String.replace(~r{<[^>]+>}, "")
    |> String.replace("&gt;", ">")
    |> String.replace("&lt;", "<")
    |> String.replace("&amp;", "&")
    |> String.replace(~r/[ \t]+/, " ")
  end
end
