defmodule Vws.Test.XMLLint do
  @moduledoc """
  Validates MTConnect documents with `xmllint` against the official 2.5 schemas, found only in
  the directory `$VWS_MTCONNECT_SCHEMAS` names, else in `../shared/mtconnect` beside the project
  (as in CI). Without them, the tests tagged `:mtconnect_schemas` are excluded by
  `test/test_helper.exs`, which says why (issue 25 item 6: `mix test` passes on a bare clone).
  """

  import ExUnit.Assertions

  @schemas %{
    devices: "MTConnectDevices_2.5_1.0.xsd",
    streams: "MTConnectStreams_2.5_1.0.xsd",
    error: "MTConnectError_2.5_1.0.xsd"
  }

  @doc """
  The directory holding the schemas, or nil: `$VWS_MTCONNECT_SCHEMAS` when set (and only it),
  else `../shared/mtconnect` of the project's root.
  """
  def schema_dir do
    dir =
      case System.get_env("VWS_MTCONNECT_SCHEMAS") do
        nil -> Path.expand("../shared/mtconnect", Path.dirname(Mix.Project.project_file()))
        dir -> Path.expand(dir)
      end

    if File.regular?(Path.join(dir, @schemas.streams)), do: dir
  end

  @doc "Why the schema-validating tests cannot run here, in words (nil when they can)."
  def missing_schemas do
    case {schema_dir(), System.get_env("VWS_MTCONNECT_SCHEMAS")} do
      {dir, _} when dir != nil ->
        nil

      {nil, nil} ->
        "the MTConnect 2.5 schemas are not in ../shared/mtconnect beside the project " <>
          "(set VWS_MTCONNECT_SCHEMAS to their directory)"

      {nil, env} ->
        "VWS_MTCONNECT_SCHEMAS=#{env} holds no #{@schemas.streams}"
    end
  end

  @doc """
  Asserts that `xml` (iodata) validates against the schema of `kind` (`:devices`, `:streams`,
  `:error`, or `:assets`: the MTConnectAssets structure the standard's text asks for, in
  `test/support/mtconnect_assets_header.xsd`, written here since the Institute's Assets schema
  is not among the shipped ones); returns the text.
  """
  def validate!(xml, kind) do
    xmllint =
      System.find_executable("xmllint") ||
        flunk("xmllint is missing: apt-get install -y libxml2-utils")

    text = IO.iodata_to_binary(xml)
    path = Path.join(System.tmp_dir!(), "vws-mtc-#{System.unique_integer([:positive])}.xml")
    File.write!(path, text)

    try do
      schema =
        if kind == :assets,
          do: Path.expand("mtconnect_assets_header.xsd", __DIR__),
          else: Path.join(schema_dir() || flunk(missing_schemas()), Map.fetch!(@schemas, kind))

      {out, status} =
        System.cmd(xmllint, ["--noout", "--schema", schema, path], stderr_to_stdout: true)

      assert status == 0, "#{kind} document does not validate:\n#{out}\n#{text}"
      text
    after
      File.rm(path)
    end
  end
end
