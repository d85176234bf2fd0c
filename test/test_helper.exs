# assert_receive waits up to 2 s by default: a loaded CI machine must not fail a correct test.
#
# max_cases: the suite waits far more than it computes — about 900 s of test time for about 120 s
# of CPU — on simulated floors, timeouts and OS processes, so async modules run 8 per scheduler
# (16 on a 2-core machine) rather than ExUnit's 2. The long campaigns are split into modules
# (crash campaign, DNC bit flips, the stateful safety test) so that they overlap too.
ExUnit.start(
  capture_log: true,
  assert_receive_timeout: 2_000,
  max_cases: System.schedulers_online() * 8
)
