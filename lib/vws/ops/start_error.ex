defmodule Vws.Ops.StartError do
  @moduledoc """
  Why a workstation could not start, in one line of words — for `mix vws.serve`, `mix vws.demo`
  and a release, which print it and exit with status 1 instead of running on without their
  workstation (`Vws.Application`). The innermost reason of a supervisor's failed child is the
  one told: a WC port in use, a journal directory another OS process holds, a listen address
  without an allow-list.

      iex> Vws.Ops.StartError.describe({:cannot_listen, "tcp://127.0.0.1:7070", %Vws.Links.Transport.Error{reason: :eaddrinuse}})
      "WC port 7070 is in use (tcp://127.0.0.1:7070)"
      iex> Vws.Ops.StartError.describe({:shutdown, {:failed_to_start_child, :sun_comm, "no allow-list"}})
      "no allow-list"
      iex> Vws.Ops.StartError.describe({:shutdown, {:failed_to_start_child, Vws.Ops.Web.Server, {:cannot_listen, "127.0.0.1", 4000, :eaddrinuse}}})
      "HTTP port 4000 is in use (127.0.0.1:4000)"
  """

  @doc "The reason, in words (an Elixir term only for a reason nothing here knows)."
  @spec describe(term) :: String.t()
  def describe({:shutdown, reason}), do: describe(reason)
  def describe({:failed_to_start_child, _child, reason}), do: describe(reason)
  def describe({:bad_return, {_mfa, {:error, reason}}}), do: describe(reason)
  def describe({:error, reason}), do: describe(reason)

  def describe({:cannot_listen, endpoint, reason}) when is_binary(endpoint) do
    port_words(endpoint, reason) ||
      "cannot listen on #{endpoint}: #{describe(reason)}"
  end

  # the dashboard's listener (Vws.Ops.Web.Server)
  def describe({:cannot_listen, bind, port, reason}) when is_integer(port) do
    case reason do
      :eaddrinuse ->
        "HTTP port #{port} is in use (#{bind}:#{port})"

      :eacces ->
        "HTTP port #{port} may not be opened by this user (ports below 1024 need privileges)"

      :eaddrnotavail ->
        "HTTP address #{bind} is not an address of this host"

      other ->
        "cannot listen on #{bind}:#{port}: #{describe(other)}"
    end
  end

  def describe({%{__exception__: true} = e, _stacktrace}), do: Exception.message(e)
  def describe(%{__exception__: true} = e), do: Exception.message(e)
  def describe({:already_started, _pid}), do: "a workstation with this id already runs here"
  def describe(reason) when is_binary(reason), do: reason

  # a tagged text ({:wc_link_policy, "tcp://0.0.0.0:7070 is not a loopback address: …"}): the text
  def describe({tag, text}) when is_atom(tag) and is_binary(text), do: text
  def describe(reason), do: inspect(reason, limit: 10)

  # "WC port 7070 is in use", "WC port 80 needs root …": what an operator can act on
  defp port_words(endpoint, %{__exception__: true, reason: reason}),
    do: port_words(endpoint, reason)

  defp port_words(endpoint, reason) do
    case URI.parse(endpoint) do
      %URI{scheme: "tcp", host: host, port: port} when is_integer(port) ->
        case reason do
          :eaddrinuse ->
            "WC port #{port} is in use (#{endpoint})"

          :eacces ->
            "WC port #{port} may not be opened by this user (ports below 1024 need privileges)"

          :eaddrnotavail ->
            "WC address #{host} is not an address of this host (#{endpoint})"

          _ ->
            nil
        end

      _ ->
        nil
    end
  end
end
