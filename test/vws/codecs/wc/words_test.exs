defmodule Vws.Codecs.WC.WordsTest do
  # Issue 24 C: no WC status ever carries an Elixir term — every ERROR text is upper-case words
  # and numbers. Over any term (Words.of/1, the one home), over whatever a partition module
  # returns or raises (Vws.CEC.Partition.run/2); MONARCH's link errors: error_paths_test.exs.
  use ExUnit.Case, async: true
  use Vws.PropCase

  alias Vws.Codecs.WC.Words

  doctest Words

  # a partition module that ends its command with whatever the test put in the command's text
  defmodule AnyResult do
    @behaviour Vws.CEC.Partition.CommandSet
    def device, do: "TEST DEVICE"
    def parse(_text), do: {:ok, :on}
    def execute(_command, ctx), do: ctx.options[:result]
  end

  # printable text, lower case and punctuation included ("VAL II error: bad", "{:ok, 1}")
  defp text do
    :proper_types.bind(
      :proper_types.list(:proper_types.range(32, 126)),
      &List.to_string/1,
      false
    )
  end

  defp term do
    :proper_types.oneof([
      :proper_types.any(),
      :proper_types.binary(),
      text(),
      :proper_types.atom(),
      {:error, :proper_types.any()},
      {:error, text()},
      :proper_types.list(:proper_types.any())
    ])
  end

  test "property: any term in words is a status text" do
    property =
      :proper.forall(term(), fn t ->
        words = Words.of(t)
        Words.text?(words) and words != "" and String.length(words) <= 80
      end)

    assert_property(property, 2_000)
  end

  test "property: whatever a partition's module returns, the command ends DONE or ERROR in words" do
    ws = "words-#{System.unique_integer([:positive])}"
    {:ok, _} = Vws.CEC.Mailbox.Owner.start_link(workstation: ws)

    property =
      :proper.forall(term(), fn result ->
        ExUnit.CaptureLog.capture_log(fn -> send(self(), {:result, run_any(ws, result)}) end)

        assert_received {:result, ended}

        case ended do
          :done -> result == :done
          {:error, text} -> Words.text?(text) and text != "" and frames?(text)
        end
      end)

    assert_property(property, 1_000)
  end

  test "a reason ending in a newline is no status text: it ends ERROR in words the WC link frames" do
    # PCRE's $ matches before a final newline: "LOST\n" passed text?/1, the command ended
    # "ERROR LOST\n", and SUN_COMM crashed framing its status reply (error_paths_test, a seed)
    refute Words.text?("LOST\n")
    refute Words.text?("\n")
    assert Words.text?("LOST")
    assert Words.of("lost\n") == "LOST"

    ws = "words-nl-#{System.unique_integer([:positive])}"
    {:ok, _} = Vws.CEC.Mailbox.Owner.start_link(workstation: ws)

    for reason <- ["LOST\n", "\n", "A\r\n"] do
      {:error, text} = run_any(ws, {:error, reason})
      assert Words.text?(text) and text != "" and frames?(text), inspect(text)
    end
  end

  # a command of AnyResult run by the partition's one path, ending with `result`
  defp run_any(ws, result) do
    Vws.CEC.Partition.run(AnyResult, %{
      workstation: ws,
      partition: :vacuum,
      number: 1,
      text: "ON",
      link: :test,
      interlocks: :off,
      options: [result: result]
    })
  end

  # the status reply a WC poll gets for a command that ended ERROR with `text` (cut to what a
  # reply carries, as SUN_COMM's answer is) can be framed
  defp frames?(text) do
    answer = Vws.Codecs.WC.Reply.truncate_status_text("0001ERROR " <> text)
    Vws.Codecs.WC.Reply.encode({:status, 1, answer})
    true
  rescue
    ArgumentError -> false
  end

  # every DNC link error MONARCH reports: test/vws/cec/error_paths_test.exs
end
