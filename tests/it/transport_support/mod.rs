//! Helpers for tests that run `minflow` nodes as separate processes: spawning with a kill
//! guard, draining their output while they run, waiting with a deadline, reading bags back
//! as raw message bytes.

#![allow(dead_code)]

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use minflow::bag::{bag_paths, BagReader};

/// A child process killed on drop (tests never leak nodes). Its stdout and stderr are read
/// by threads of their own while it runs: a child whose output nobody reads stalls once a
/// pipe's 64 KiB are full (a DDS node at `RUST_LOG=info` logs discovery every few seconds).
pub struct Node {
    pub child: Option<Child>,
    pub name: String,
    stdout: Drain,
    stderr: Drain,
}

/// Everything one pipe of a child said so far, read by a thread until the pipe closes.
struct Drain {
    text: Arc<Mutex<Vec<u8>>>,
    thread: Option<JoinHandle<()>>,
}

impl Drain {
    fn start(mut pipe: impl Read + Send + 'static) -> Drain {
        let text = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&text);
        let thread = std::thread::spawn(move || {
            let mut buf = [0u8; 8192];
            while let Ok(n @ 1..) = pipe.read(&mut buf) {
                sink.lock().unwrap().extend_from_slice(&buf[..n]);
            }
        });
        Drain {
            text,
            thread: Some(thread),
        }
    }

    /// Waits until the pipe closed (the child exited) and returns all it said.
    fn finish(&mut self) -> Vec<u8> {
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        std::mem::take(&mut *self.text.lock().unwrap())
    }

    fn now(&self) -> String {
        String::from_utf8_lossy(&self.text.lock().unwrap()).into_owned()
    }
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
/// tests, 4 the record/replay round trip, 5 the node against offline predictions, 6 the
/// node on frames of 40,000 particles.
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
        let mut cmd = Command::new(minflow_bin());
        cmd.args(args)
            .env("RUST_LOG", "info")
            .envs(env.iter().map(|(k, v)| (k, v)));
        Node::start(name, &mut cmd)
    }

    /// `minflow record --transport T --topic TOPIC -o OUT --count N` with `env`, as a node
    /// named "record": the recorder every closed-loop test reads its predictions back with.
    pub fn record(
        transport: &str,
        topic: &str,
        out: &Path,
        count: usize,
        env: &[(&str, String)],
    ) -> Node {
        let count = count.to_string();
        let args = [
            "record",
            "--transport",
            transport,
            "--topic",
            topic,
            "-o",
            out.to_str().unwrap(),
            "--count",
            &count,
        ];
        Node::spawn_env("record", &args, env)
    }

    /// Starts `cmd` with its stdout and stderr piped to threads that keep what it says.
    pub fn start(name: &str, cmd: &mut Command) -> Node {
        let mut child = cmd
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {name}: {e}"));
        let stdout = Drain::start(child.stdout.take().unwrap());
        let stderr = Drain::start(child.stderr.take().unwrap());
        Node {
            child: Some(child),
            name: name.into(),
            stdout,
            stderr,
        }
    }

    /// Waits for exit (killing the process at the deadline) and returns its output.
    pub fn wait(self, timeout: Duration) -> Output {
        let name = self.name.clone();
        self.wait_or_kill(timeout).unwrap_or_else(|out| {
            panic!(
                "{name} did not finish within {timeout:?}; stderr:\n{}",
                String::from_utf8_lossy(&out.stderr)
            )
        })
    }

    /// Waits for exit at most `timeout`: its output, or (`Err`) what it said before it was
    /// killed at the deadline.
    pub fn wait_or_kill(mut self, timeout: Duration) -> Result<Output, Output> {
        let mut child = self.child.take().unwrap();
        let deadline = Instant::now() + timeout;
        let (status, in_time) = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break (status, true);
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                break (child.wait().unwrap(), false);
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let output = Output {
            status,
            stdout: self.stdout.finish(),
            stderr: self.stderr.finish(),
        };
        if in_time {
            Ok(output)
        } else {
            Err(output)
        }
    }

    /// Waits (at most `timeout`) for a line of stderr starting with `prefix` and returns the
    /// rest of that line; panics with what the process said when none came.
    pub fn wait_for_stderr_line(&self, prefix: &str, timeout: Duration) -> String {
        let deadline = Instant::now() + timeout;
        loop {
            let said = self.stderr.now();
            // Whole lines only: the pipe may have delivered half of the last one.
            let whole = &said[..said.rfind('\n').map_or(0, |i| i + 1)];
            if let Some(rest) = whole.lines().find_map(|l| l.strip_prefix(prefix)) {
                return rest.trim().to_owned();
            }
            assert!(
                Instant::now() < deadline,
                "{} never said {prefix:?}:\n{said}",
                self.name
            );
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

/// The last 40 lines of a process's stderr that are not the DDS stack's discovery chatter
/// (its multi-line locator updates), for a failure message.
pub fn log_tail(stderr: &[u8]) -> String {
    let text = String::from_utf8_lossy(stderr);
    let lines: Vec<&str> = text
        .lines()
        .filter(|l| {
            !l.starts_with(' ')
                && ![
                    "Locators in ReaderProxy",
                    "INFO Unicast:",
                    "INFO Multicast:",
                ]
                .iter()
                .any(|chatter| l.contains(chatter))
        })
        .collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
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

/// `multi` scene `scene` (seed 0) simulated on 256^2 into `dir`, 40,000 particles and
/// `frames` frames (`simulate --grid 256`, about 800 kB of CDR a frame): its bag.
pub fn scene_of_40000(dir: &Path, scene: u32, frames: u32) -> PathBuf {
    let (scene, frames) = (scene.to_string(), frames.to_string());
    let out = dir.to_str().unwrap();
    let args = [
        "simulate", "--family", "multi", "--scenes", &scene, "--grid", "256", "--frames", &frames,
        "--out", out,
    ];
    let o = Node::spawn("simulate", &args).wait(Duration::from_secs(120));
    ok(&o, "simulate --grid 256");
    let mut bags = bag_paths(&[dir.to_path_buf()]).unwrap();
    assert_eq!(bags.len(), 1, "{bags:?}");
    bags.remove(0)
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
