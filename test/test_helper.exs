# assert_receive waits up to 2 s by default: a loaded CI machine must not fail a correct test.
ExUnit.start(capture_log: true, assert_receive_timeout: 2_000)
