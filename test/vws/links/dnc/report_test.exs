defmodule Vws.Links.DNC.ReportTest do
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Links.DNC.Report

  doctest Report

  test "status reports are read back; anything else is refused" do
    report = %{state: :active, program: "000042", alarm: 12}
    assert Report.parse_status(Report.status(report)) == {:ok, report}
    assert Report.parse_status("STATE=BUSY;PROG=000042;ALARM=0") == {:error, :bad_status_report}
    assert Report.parse_status("STATE=IDLE;PROG=42;ALARM=0") == {:error, :bad_status_report}
    assert Report.parse_status("") == {:error, :bad_status_report}
  end

  test "tool offsets: golden lines, blank lines skipped, bad lines refused" do
    assert Report.offsets([{7, 123.456}, {12, -0.00004}]) == "07 +123.4560\n12 -000.0000\n"
    assert Report.parse_offsets("\n03 -001.5000\r\n\n") == {:ok, %{3 => "-001.5000"}}
    assert Report.parse_offsets("03 1.5\n") == {:error, {:bad_line, "03 1.5"}}
  end

  test "every offset table is read back with the same line numbers and values" do
    gen =
      :proper_types.list({:proper_types.integer(0, 99), :proper_types.float(-999.9999, 999.9999)})

    property =
      :proper.forall(gen, fn table ->
        table = Map.to_list(Map.new(table))
        {:ok, parsed} = Report.parse_offsets(Report.offsets(table))

        Enum.sort(Map.keys(parsed)) == Enum.sort(Enum.map(table, &elem(&1, 0))) and
          Enum.all?(table, fn {n, v} ->
            abs(String.to_float(parsed[n]) - v) <= 0.00005 + 1.0e-9
          end)
      end)

    assert_property(property, 200)
  end
end
