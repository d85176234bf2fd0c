defmodule Vws.Ops.Web.TokensTest do
  # Issue 30 item 5: the tokens come from files or the environment, never from a command line.
  # Not async: it sets the process environment's VWS_HTTP_* variables.
  use ExUnit.Case, async: false

  alias Vws.Ops.Web.Tokens

  doctest Tokens

  @vars ~w(VWS_HTTP_TOKEN VWS_HTTP_TOKEN_FILE VWS_HTTP_READ_TOKEN VWS_HTTP_READ_TOKEN_FILE)

  setup do
    saved = for var <- @vars, do: {var, System.get_env(var)}
    Enum.each(@vars, &System.delete_env/1)

    on_exit(fn ->
      for {var, value} <- saved,
          do: if(value, do: System.put_env(var, value), else: System.delete_env(var))
    end)
  end

  defp token_file(dir, name, text, mode \\ 0o600) do
    path = Path.join(dir, name)
    File.write!(path, text)
    File.chmod!(path, mode)
    path
  end

  @tag :tmp_dir
  test "a file given, else the file in the environment, else the environment's value, else none",
       %{tmp_dir: dir} do
    assert Tokens.control() == {:ok, nil}
    assert Tokens.read() == {:ok, nil}

    System.put_env("VWS_HTTP_TOKEN", "  from-env \n")
    System.put_env("VWS_HTTP_READ_TOKEN", "read-env")
    assert Tokens.control() == {:ok, "from-env"}
    assert Tokens.read() == {:ok, "read-env"}

    System.put_env("VWS_HTTP_TOKEN_FILE", token_file(dir, "env-file", "from-env-file\n"))
    System.put_env("VWS_HTTP_READ_TOKEN_FILE", token_file(dir, "read-file", "read-file\n", 0o640))
    assert Tokens.control() == {:ok, "from-env-file"}
    assert Tokens.read() == {:ok, "read-file"}

    given = token_file(dir, "given", "from-given-file\nsecond line is not the token\n")
    assert Tokens.control(given) == {:ok, "from-given-file"}
    assert Tokens.read(given) == {:ok, "from-given-file"}
  end

  @tag :tmp_dir
  test "a token file that is empty, readable by every user, missing or a directory is refused in words",
       %{tmp_dir: dir} do
    empty = token_file(dir, "empty", " \n")
    assert {:error, "the control token file " <> rest} = Tokens.control(empty)
    assert rest == "#{empty} is empty"

    open = token_file(dir, "open", "secret\n", 0o644)
    assert {:error, message} = Tokens.read(open)
    assert message == "the read token file #{open} is readable by every user: chmod 0600 it"

    System.put_env("VWS_HTTP_TOKEN_FILE", Path.join(dir, "missing"))

    assert Tokens.control() ==
             {:error,
              "cannot read the control token (VWS_HTTP_TOKEN_FILE) from " <>
                "#{Path.join(dir, "missing")}: no such file or directory"}

    assert {:error, message} = Tokens.control(dir)
    assert message =~ "is a directory, not a regular file"
  end

  test "mix vws.serve refuses a token on its command line, saying to use a file" do
    for {flag, file_flag, var} <- [
          {"--http-token", "--http-token-file", "VWS_HTTP_TOKEN"},
          {"--http-read-token", "--http-read-token-file", "VWS_HTTP_READ_TOKEN"}
        ] do
      error =
        assert_raise Mix.Error, fn ->
          Mix.Tasks.Vws.Serve.run([flag, "s3cret", "--no-journal"])
        end

      assert error.message =~ "#{flag} puts the token on the command line"
      assert error.message =~ "give #{file_flag} PATH"
      assert error.message =~ "#{var}_FILE"
      refute error.message =~ "s3cret"
    end
  end

  @tag :tmp_dir
  test "mix vws.serve refuses a token file others can read before starting anything",
       %{tmp_dir: dir} do
    open = token_file(dir, "open", "secret\n", 0o644)

    error =
      assert_raise Mix.Error, fn ->
        Mix.Tasks.Vws.Serve.run(["--http-token-file", open, "--no-journal"])
      end

    assert error.message =~ "is readable by every user"
  end
end
