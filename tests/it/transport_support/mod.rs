//! Helpers for tests that run `minflow` nodes as separate processes: spawning with a kill
//! guard, waiting with a deadline, reading bags back as raw message bytes.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use minflow::bag::{bag_paths, BagReader};

/// A child process killed on drop (tests never leak nodes).
pub struct Node {
    pub child: Option<Child>,
    pub name: String,
}

/// The `minflow` binary the tests run: `$MINFLOW_BIN` when set (a copy of this build's
/// binary, where several worktrees share one target folder), else cargo's.
pub fn minflow_bin() -> PathBuf {
    std::env::var_os("MINFLOW_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_minflow")))
}

/// A ROS domain of its own for the DDS processes of test `index` (0..8) of this process:
/// 100..=227 by pid, so DDS tests running at once do not share discovery in domain 0 (a
/// full run once saw a node's participant find port 7400 taken by another test's), and
/// test runs of several checkouts on one machine rarely share one. Indices: 0..4 the rclpy
/// tests, 4 the record/replay round trip, 5 the node against offline predictions.
pub fn test_domain(index: u32) -> String {
    (100 + (std::process::id() % 16) * 8 + index).to_string()
}

/// `ROS_DOMAIN_ID` of test `index`'s own domain ([`test_domain`]) for the ros2 transport,
/// nothing for the others.
pub fn domain_env(transport: &str, index: u32) -> Vec<(&'static str, String)> {
    match transport {
        "ros2" => vec![("ROS_DOMAIN_ID", test_domain(index))],
        _ => vec![],
    }
}

impl Node {
    pub fn spawn(name: &str, args: &[&str]) -> Node {
        Node::spawn_env(name, args, &[])
    }

    /// [`Node::spawn`] with more environment variables.
    pub fn spawn_env(name: &str, args: &[&str], env: &[(&str, String)]) -> Node {
        let child = Command::new(minflow_bin())
            .args(args)
            .env("RUST_LOG", "info")
            .envs(env.iter().map(|(k, v)| (k, v)))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {name}: {e}"));
        Node {
            child: Some(child),
            name: name.into(),
        }
    }

    /// Waits for exit (killing the process at the deadline) and returns its output.
    pub fn wait(mut self, timeout: Duration) -> Output {
        let mut child = self.child.take().unwrap();
        let deadline = Instant::now() + timeout;
        loop {
            if child.try_wait().unwrap().is_some() {
                return child.wait_with_output().unwrap();
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                let out = child.wait_with_output().unwrap();
                panic!(
                    "{} did not finish within {timeout:?}; stderr:\n{}",
                    self.name,
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Sends `signal` (e.g. "KILL", "TERM") to the process.
    pub fn signal(&self, signal: &str) {
        let pid = self.child.as_ref().unwrap().id().to_string();
        let ok = Command::new("kill")
            .args([&format!("-{signal}"), &pid])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill -{signal} {pid}");
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Asserts success and returns stderr.
pub fn ok(out: &Output, what: &str) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        out.status.success(),
        "{what} failed ({:?}):\n{stderr}",
        out.status
    );
    stderr
}

/// A topic no other test uses: `/minflow_test_<pid>_<n>_<tag>/frames`.
pub fn unique_topic(tag: &str) -> String {
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "/minflow_test_{}_{}_{tag}/frames",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}

/// The bundled bag used as the source.
pub fn source_bag() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/multi_rope+snow_001.mcap")
}

/// The raw bytes of every message on `topic` (all topics when None) in file order, over
/// the bags of `input` (file or folder), stopping quietly at a truncation.
pub fn raw_messages(input: &Path, topic: Option<&str>) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for path in bag_paths(&[input.to_path_buf()]).unwrap() {
        for m in BagReader::open(&path).unwrap() {
            let Ok(m) = m else { break };
            if topic.is_none_or(|t| m.topic() == t) {
                out.push(m.data);
            }
        }
    }
    out
}

/// Parses `name=value` from a node's counter line (last occurrence).
pub fn counter(stderr: &str, name: &str) -> Option<u64> {
    let key = format!("{name}=");
    stderr.lines().rev().find_map(|line| {
        let at = line.find(&key)?;
        line[at + key.len()..]
            .split(|c: char| !c.is_ascii_digit())
            .next()?
            .parse()
            .ok()
    })
}
