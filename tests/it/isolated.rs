//! Tests that need a process of their own, inside the one test binary: burn's NdArray random
//! generator is process-wide (a training's dropout masks and weights interleave with any
//! other test drawing from it at the same time), and the ROS 2 tests set a process-wide
//! environment variable. [`run`] runs such a test's body in a child process of this same
//! binary that runs that one test and nothing else, and checks that it ran and passed.

use std::process::Command;

/// Set in the child to the name of the test whose body it runs.
const CHILD: &str = "MINFLOW_ISOLATED_TEST";

/// Runs `body` alone in a process: in the test harness's process, starts this binary again
/// filtered to exactly `path` (`module_path!()::test_name`) and asserts that it passed one
/// test; in that child, runs `body`.
///
/// # Panics
/// The child failed, or ran no test (its output is in the message).
pub fn run(path: &str, body: impl FnOnce()) {
    let name = path.split_once("::").map_or(path, |(_, rest)| rest);
    if std::env::var(CHILD).as_deref() == Ok(name) {
        body();
        return;
    }
    let out = Command::new(std::env::current_exe().expect("the test binary"))
        .args([name, "--exact", "--test-threads", "1", "--nocapture"])
        .env(CHILD, name)
        .output()
        .expect("starting the test binary");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{name} in its own process:\n{text}");
    assert!(
        text.contains("1 passed"),
        "{name} did not run in its own process:\n{text}"
    );
}
