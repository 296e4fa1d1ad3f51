//! minflow's `--transport ros2` nodes against real ROS 2: rclpy 9.1 on Fast DDS 3.2
//! (`rmw_fastrtps_cpp`, the default middleware of ROS 2 Kilted), from the PyPI wheels, with
//! `minflow_msgs` built from `msgs/` by rosidl (`tests/python/ros2_env.sh` makes and caches
//! the venv; `tests/python/ros2_peer.py` is the rclpy node). Each test runs in a ROS domain
//! of its own (Fast DDS with `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`), with a default-QoS
//! rclpy subscriber or publisher, and bounds every wait:
//!
//! - replay -> rclpy: every frame of the bundled bags at `--rate 1`, bytes identical to the
//!   bags; rclpy sees the RIHS01 type hash on minflow's writer; no ROS_DISTRO warning;
//! - rclpy -> record: every frame, bytes identical;
//! - rclpy -> node -> rclpy: a prediction per input frame at 62.5 Hz, and status reports;
//! - replay `--pointcloud2` -> rclpy: `sensor_msgs/PointCloud2` of every frame.
//!
//! When pip cannot reach the package registry the tests fail, saying so, unless told to skip
//! ([`crate::unavailable`]).

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::sync::OnceLock;
use std::time::Duration;

use crate::transport_support::{ok, raw_messages, source_bag, test_domain, unique_topic, Node};
use crate::unavailable::cannot_run;
use minflow::msgs::type_hash::minflow_type_hash;
use minflow::msgs::TYPE_NAME;

/// Exit status of ros2_env.sh when pip cannot reach the registry.
const NO_REGISTRY: i32 = 4;

/// The environment lines of `tests/python/ros2_env.sh` (runs once per test process), or None
/// when the wheels cannot be had because the registry is unreachable: the calling test then
/// fails, or returns where the user opted out ([`cannot_run`]).
fn ros2_env() -> Option<&'static HashMap<String, String>> {
    static ENV: OnceLock<Result<HashMap<String, String>, String>> = OnceLock::new();
    let env = ENV.get_or_init(|| {
        let script = root().join("tests/python/ros2_env.sh");
        let out = Command::new("bash")
            .arg(&script)
            .output()
            .expect("running tests/python/ros2_env.sh");
        let stderr = String::from_utf8_lossy(&out.stderr);
        if out.status.code() == Some(NO_REGISTRY) {
            return Err(format!(
                "ROS 2 interop needs the PyPI wheels: {}",
                stderr.trim()
            ));
        }
        assert!(out.status.success(), "ros2_env.sh failed:\n{stderr}");
        let vars = String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter_map(|l| l.strip_prefix("export "))
            .filter_map(|l| l.split_once('='))
            .map(|(k, v)| (k.to_owned(), v.trim_matches('\'').to_owned()))
            .collect();
        Ok(vars)
    });
    match env {
        Ok(vars) => Some(vars),
        Err(why) => {
            cannot_run(why);
            None
        }
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// An rclpy process of `tests/python/ros2_peer.py` in `domain`, stdout piped by lines.
struct Peer {
    child: Child,
    lines: Receiver<String>,
}

impl Peer {
    fn spawn(env: &HashMap<String, String>, domain: &str, args: &[&str]) -> Peer {
        let mut child = Command::new(&env["MINFLOW_ROS2_PYTHON"])
            .arg(root().join("tests/python/ros2_peer.py"))
            .args(args)
            .envs(env)
            .env("ROS_DOMAIN_ID", domain)
            .env("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting ros2_peer.py");
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Peer { child, lines }
    }

    /// Waits (at most `timeout`) for the `ready` line of a subscriber.
    fn ready(&self, timeout: Duration) {
        let line = self.lines.recv_timeout(timeout).expect("rclpy never ready");
        assert_eq!(line, "ready");
    }

    /// Waits (at most `timeout`) for the JSON summary line and the exit.
    fn summary(mut self, timeout: Duration) -> serde_json::Value {
        let line = self.lines.recv_timeout(timeout);
        let status = self.child.wait().expect("waiting for rclpy");
        let mut stderr = String::new();
        if let Some(mut e) = self.child.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut e, &mut stderr);
        }
        let line = line.unwrap_or_else(|_| panic!("no summary from rclpy ({status}):\n{stderr}"));
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("{line:?}: {e}\n{stderr}"))
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A minflow node in `domain`.
fn minflow(domain: &str, name: &str, args: &[&str]) -> Node {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_minflow"));
    cmd.args(args)
        .env("ROS_DOMAIN_ID", domain)
        .env_remove("ROS_DISTRO");
    Node::start(name, &mut cmd)
}

/// Records of `ros2_peer.py --out` (u32 LE length + bytes).
fn read_records(path: &Path) -> Vec<Vec<u8>> {
    let data = std::fs::read(path).expect("rclpy's output file");
    let mut out = Vec::new();
    let mut at = 0;
    while at + 4 <= data.len() {
        let n = u32::from_le_bytes(data[at..at + 4].try_into().unwrap()) as usize;
        out.push(data[at + 4..at + 4 + n].to_vec());
        at += 4 + n;
    }
    out
}

fn write_records(path: &Path, records: &[Vec<u8>]) {
    let mut data = Vec::new();
    for r in records {
        data.extend_from_slice(&(r.len() as u32).to_le_bytes());
        data.extend_from_slice(r);
    }
    std::fs::write(path, data).unwrap();
}

/// The frames of the bundled bags in the order `replay` plays them (by log time, ties by
/// bag order).
fn bag_frames_in_play_order() -> Vec<Vec<u8>> {
    use minflow::bag::{bag_paths, BagReader};
    let mut all = Vec::new();
    for (bag, path) in bag_paths(&[root().join("bags")])
        .unwrap()
        .iter()
        .enumerate()
    {
        for (i, m) in BagReader::open(path).unwrap().enumerate() {
            let m = m.unwrap();
            if m.topic() == "/mpm/frames" {
                all.push((m.log_time, bag, i, m.data));
            }
        }
    }
    all.sort_by_key(|(t, bag, i, _)| (*t, *bag, *i));
    all.into_iter().map(|(_, _, _, d)| d).collect()
}

const WAIT: Duration = Duration::from_secs(60);

#[test]
fn replay_reaches_a_default_qos_rclpy_subscriber_every_frame() {
    let Some(env) = ros2_env() else { return };
    let dom = test_domain(0);
    let topic = unique_topic("rclpy_replay");
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("frames.bin");
    let expected = bag_frames_in_play_order();
    assert_eq!(expected.len(), 150);
    let sub = Peer::spawn(
        env,
        &dom,
        &[
            "sub",
            &topic,
            "--count",
            "150",
            "--timeout",
            "60",
            "--idle",
            "10",
            "--out",
            out.to_str().unwrap(),
        ],
    );
    sub.ready(WAIT);
    let bags = root().join("bags");
    let replay = minflow(
        &dom,
        "replay",
        &[
            "replay",
            bags.to_str().unwrap(),
            "--transport",
            "ros2",
            "--rate",
            "1",
            "--topic",
            &topic,
        ],
    );
    let stderr = ok(&replay.wait(WAIT), "replay");
    assert!(!stderr.contains("ROS_DISTRO"), "distro warning:\n{stderr}");
    let summary = sub.summary(WAIT);
    assert_eq!(summary["received"], 150, "{summary}\nreplay:\n{stderr}");
    let got = read_records(&out);
    assert_eq!(got.len(), 150);
    for (i, (g, e)) in got.iter().zip(&expected).enumerate() {
        assert!(g == e, "frame {i}: bytes differ from the bag's");
    }
    let hash = minflow_type_hash(TYPE_NAME).unwrap();
    assert_eq!(
        summary["type_hashes"],
        serde_json::json!([hash]),
        "{summary}"
    );
}

#[test]
fn rclpy_publisher_to_record_every_frame() {
    let Some(env) = ros2_env() else { return };
    let dom = test_domain(1);
    let topic = unique_topic("rclpy_record");
    let dir = crate::tmp::tempdir().unwrap();
    let frames = raw_messages(&root().join("bags"), Some("/mpm/frames"));
    assert_eq!(frames.len(), 150);
    let file = dir.path().join("frames.bin");
    write_records(&file, &frames);
    let bag = dir.path().join("rec");
    let record = minflow(
        &dom,
        "record",
        &[
            "record",
            "--transport",
            "ros2",
            "--topic",
            &topic,
            "--out",
            bag.to_str().unwrap(),
            "--count",
            "150",
            "--idle-exit",
            "10",
        ],
    );
    // 62.5 frames a second, the bags' own rate per scene.
    let publisher = Peer::spawn(
        env,
        &dom,
        &[
            "pub",
            &topic,
            "--frames",
            file.to_str().unwrap(),
            "--hz",
            "62.5",
            "--timeout",
            "40",
        ],
    );
    let summary = publisher.summary(WAIT);
    assert_eq!(summary["published"], 150, "{summary}");
    ok(&record.wait(WAIT), "record");
    let got = raw_messages(&bag, Some(&topic));
    assert_eq!(got.len(), 150, "frames recorded");
    assert!(got == frames, "recorded bytes differ from what rclpy sent");
}

#[test]
fn rclpy_to_node_to_rclpy_with_status() {
    let Some(env) = ros2_env() else { return };
    let dom = test_domain(2);
    let input = unique_topic("rclpy_node_in");
    let output = unique_topic("rclpy_node_out");
    let status = format!("{}/status", output.trim_end_matches("/frames"));
    let dir = crate::tmp::tempdir().unwrap();
    let frames = raw_messages(&source_bag(), Some("/mpm/frames"));
    let file = dir.path().join("frames.bin");
    write_records(&file, &frames);
    let n = frames.len().to_string();
    let model = root().join("models/all-grid-mingru-small");
    let predictions = Peer::spawn(
        env,
        &dom,
        &[
            "sub",
            &output,
            "--count",
            &n,
            "--timeout",
            "60",
            "--idle",
            "10",
        ],
    );
    let statuses = Peer::spawn(
        env,
        &dom,
        &[
            "sub",
            &status,
            "--type",
            "status",
            "--count",
            "2",
            "--timeout",
            "60",
        ],
    );
    predictions.ready(WAIT);
    statuses.ready(WAIT);
    let node = minflow(
        &dom,
        "node",
        &[
            "node",
            "--transport",
            "ros2",
            "--model",
            model.to_str().unwrap(),
            "--in",
            &input,
            "--out",
            &output,
            "--status",
            &status,
            "--name",
            "rclpy_test",
            "--wait-for-subscribers",
            "1",
            // Every frame predicted however busy the machine (the default 8 drops the oldest).
            "--queue-depth",
            "64",
        ],
    );
    let publisher = Peer::spawn(
        env,
        &dom,
        &[
            "pub",
            &input,
            "--frames",
            file.to_str().unwrap(),
            "--hz",
            "62.5",
            "--timeout",
            "40",
        ],
    );
    assert_eq!(publisher.summary(WAIT)["published"], frames.len());
    let got = predictions.summary(WAIT);
    assert_eq!(got["received"], frames.len(), "predictions: {got}");
    let got = statuses.summary(WAIT);
    assert_eq!(got["received"], 2, "{got}");
    assert_eq!(got["status"]["node"], "rclpy_test", "{got}");
    node.signal("INT");
    ok(&node.wait(WAIT), "node");
}

#[test]
fn replay_pointcloud2_reaches_rclpy() {
    let Some(env) = ros2_env() else { return };
    let dom = test_domain(3);
    let topic = unique_topic("rclpy_cloud_frames");
    let cloud = unique_topic("rclpy_cloud").replace("/frames", "/cloud");
    let sub = Peer::spawn(
        env,
        &dom,
        &[
            "sub",
            &cloud,
            "--type",
            "pointcloud2",
            "--count",
            "25",
            "--timeout",
            "60",
        ],
    );
    sub.ready(WAIT);
    let bag = source_bag();
    let replay = minflow(
        &dom,
        "replay",
        &[
            "replay",
            bag.to_str().unwrap(),
            "--transport",
            "ros2",
            "--topic",
            &topic,
            "--pointcloud2",
            &cloud,
        ],
    );
    ok(&replay.wait(WAIT), "replay");
    let got = sub.summary(WAIT);
    assert_eq!(got["received"], 25, "{got}");
    let c = &got["cloud"];
    assert_eq!(c["frame_id"], "world");
    assert_eq!(
        (c["width"].as_u64(), c["height"].as_u64()),
        (Some(2500), Some(1))
    );
    assert_eq!(
        (c["point_step"].as_u64(), c["row_step"].as_u64()),
        (Some(16), Some(40_000))
    );
    assert_eq!(c["data_len"], 40_000);
    assert_eq!(c["is_dense"], true);
    assert_eq!(
        c["fields"],
        serde_json::json!([
            ["x", 0, 7, 1],
            ["y", 4, 7, 1],
            ["z", 8, 7, 1],
            ["rgb", 12, 7, 1]
        ])
    );
    assert_eq!(
        got["type_hashes"],
        serde_json::json!([minflow::msgs::pointcloud2::type_hash().unwrap()])
    );
}
