//! What a test does when this machine lacks something it needs (the `openssl` command, the
//! Python package registry): it fails, naming what is missing, so `cargo test` never reports
//! a test passed that did not run. A user who knows the machine lacks it sets
//! `MINFLOW_SKIP_UNAVAILABLE=1` (README, "Tests"): the test then prints why on stderr
//! (shown with `--nocapture`) and returns. `.ci/run` does not set it.

/// The environment variable that turns these failures into skips.
pub const OPT_OUT: &str = "MINFLOW_SKIP_UNAVAILABLE";

/// For a test that cannot run here because of `why`: panics with `why` and how to opt out,
/// or, when [`OPT_OUT`] is `1`, prints `why` and returns, and the test returns after it.
///
/// # Panics
/// Unless [`OPT_OUT`] is `1`.
pub fn cannot_run(why: &str) {
    if std::env::var(OPT_OUT).as_deref() == Ok("1") {
        eprintln!("skipped ({OPT_OUT}=1): {why}");
        return;
    }
    panic!(
        "this test cannot run here: {why}\n\
         (set {OPT_OUT}=1 to skip the tests that need what this machine lacks)"
    );
}
