defmodule Vws.Test.XMLLint do
  @moduledoc """
  Validates MTConnect documents with `xmllint` against the official 2.5 schemas in
  `../shared/mtconnect` (beside the project, as in CI), else `/work/shared/mtconnect`, or the
  directory in `$VWS_MTCONNECT_SCHEMAS`.
  """

  import ExUnit.Assertions

  @schemas %{
    devices: "MTConnectDevices_2.5_1.0.xsd",
    streams: "MTConnectStreams_2.5_1.0.xsd",
    error: "MTConnectError_2.5_1.0.xsd"
  }

  @doc "The directory holding the schemas."
  def schema_dir do
    [
      System.get_env("VWS_MTCONNECT_SCHEMAS"),
      Path.expand("../shared/mtconnect"),
      "/work/shared/mtconnect"
    ]
    |> Enum.reject(&is_nil/1)
    |> Enum.find(&File.regular?(Path.join(&1, @schemas.streams))) ||
      flunk(
        "the MTConnect 2.5 schemas are not in ../shared/mtconnect (nor $VWS_MTCONNECT_SCHEMAS)"
      )
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
          else: Path.join(schema_dir(), Map.fetch!(@schemas, kind))

      {out, status} =
        System.cmd(xmllint, ["--noout", "--schema", schema, path], stderr_to_stdout: true)

      assert status == 0, "#{kind} document does not validate:\n#{out}\n#{text}"
      text
    after
      File.rm(path)
    end
  end
end
