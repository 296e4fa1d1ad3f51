//! Issue 35, peers that die and come back: the replay killed with SIGKILL mid-stream and
//! started again (the node serves the new stream), the node killed with SIGKILL and started
//! again over iceoryx2 (its stale shared memory is removed through iceoryx2's dead-node API,
//! and the new node serves), the recorder killed with SIGKILL while frames stream (what it
//! flushed is a readable prefix of what a second recorder got; at most about
//! `--flush-interval` of frames lost), and `launch` restarting a `respawn: true` node that was
//! killed.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use minflow::msgs::ParticleFrame;
use minflow::transport::{self, Sample, Transport};

use crate::transport_support::*;

/// The shipped CPU model (no training needed).
fn small_model() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/all-grid-mingru-small")
}

fn bag(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("bags")
        .join(name)
}

/// The node on `input` -> `output` over `transport`.
fn node(name: &str, transport: &str, input: &str, output: &str, wait: &str) -> Node {
    let model = small_model();
    Node::spawn(
        name,
        &[
            "node",
            "--model",
            model.to_str().unwrap(),
            "--transport",
            transport,
            "--in",
            input,
            "--out",
            output,
            "--wait-for-subscribers",
            wait,
            "--status",
            "none",
            "--queue-depth",
            "64",
        ],
    )
}

/// Decoded frames of the recording `out` on `topic` as (scene, frame_index).
fn recorded(out: &Path, topic: &str) -> Vec<(String, u32)> {
    raw_messages(out, Some(topic))
        .iter()
        .map(|b| {
            let f = minflow::msgs::decode(b).unwrap();
            (f.scene, f.frame_index)
        })
        .collect()
}

/// Waits (at most `timeout`) until a prediction that `wanted` accepts arrives on `rx`;
/// whether one did.
fn wait_for(
    rx: &Receiver<Sample>,
    wanted: impl Fn(&ParticleFrame) -> bool,
    timeout: Duration,
) -> bool {
    let deadline = Instant::now() + timeout;
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        match rx.recv_timeout(left) {
            Ok(s) if wanted(&s.decode().unwrap()) => return true,
            Ok(_) => {}
            Err(_) => return false,
        }
    }
    false
}

#[test]
fn replay_killed_mid_stream_then_restarted_is_served_again() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("pred");
    let (input, output) = (unique_topic("rk_in"), unique_topic("rk_out"));
    let recorder = Node::spawn(
        "record",
        &["record", "--topic", &output, "-o", out.to_str().unwrap()],
    );
    // This test watches the predictions too, to kill and stop on what it sees.
    let session = transport::zenoh::ZenohTransport::open(None).unwrap();
    let (tx, rx) = channel();
    let _sub = session.subscribe(&output, tx).unwrap();
    // It subscribes to its input once the recorder and this test subscribed to its output.
    let surrogate = node("node", "zenoh", &input, &output, "2");
    let first = bag("multi_rope+snow_001.mcap");
    let killed = Node::spawn(
        "replay 1",
        &[
            "replay",
            first.to_str().unwrap(),
            "--topic",
            &input,
            "--loop",
        ],
    );
    // Killed once the node served its stream (a prediction arrived), mid-loop.
    let served = wait_for(
        &rx,
        |f| f.scene == "multi/rope+snow/001",
        Duration::from_secs(60),
    );
    assert!(served, "the first stream was never predicted");
    killed.signal("KILL");
    drop(killed);
    let second = bag("multi_liquid+snow_000.mcap");
    let replay = Node::spawn(
        "replay 2",
        &["replay", second.to_str().unwrap(), "--topic", &input],
    );
    ok(
        &replay.wait(Duration::from_secs(60)),
        "replay after the kill",
    );
    // Stopped once the prediction of the last frame arrived (the recorder subscribes as this
    // test does), or after 10 s without it (the check below then names what is missing).
    let last = |f: &ParticleFrame| f.scene == "multi/liquid+snow/000" && f.frame_index == 25;
    wait_for(&rx, last, Duration::from_secs(10));
    surrogate.signal("INT");
    let node_log = ok(&surrogate.wait(Duration::from_secs(30)), "node");
    recorder.signal("INT");
    ok(&recorder.wait(Duration::from_secs(30)), "record");
    let frames = recorded(&out, &output);
    let after: Vec<u32> = frames
        .iter()
        .filter(|(scene, _)| scene == "multi/liquid+snow/000")
        .map(|(_, i)| *i)
        .collect();
    assert_eq!(
        after,
        (1..=25).collect::<Vec<u32>>(),
        "every frame of the restarted stream predicted, in order\n{node_log}"
    );
    assert!(
        frames.iter().any(|(s, _)| s == "multi/rope+snow/001"),
        "the killed stream was served before the kill"
    );
}

/// (alive, dead) iceoryx2 nodes of process `pid`, as iceoryx2's node list sees them.
fn iceoryx2_nodes_of(pid: u32) -> (usize, usize) {
    use iceoryx2::node::{NodeState, NodeView};
    use iceoryx2::prelude::*;
    type Svc = ipc_threadsafe::Service;
    let pid = pid.to_string();
    let of_pid = |id: &iceoryx2::identifiers::UniqueNodeId| {
        id.pid::<Svc>().is_ok_and(|p| p.to_string() == pid)
    };
    let (mut alive, mut dead) = (0, 0);
    let _ = Node::<Svc>::list(Config::global_config(), |state| {
        match &state {
            NodeState::Alive(v) if of_pid(v.id()) => alive += 1,
            NodeState::Dead(v) if of_pid(v.id()) => dead += 1,
            _ => {}
        }
        CallbackProgression::Continue
    });
    (alive, dead)
}

#[test]
fn iceoryx2_node_killed_then_restarted_cleans_up_and_serves() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("pred");
    let (input, output) = (unique_topic("nk_in"), unique_topic("nk_out"));
    let first = node("node 1", "iceoryx2", &input, &output, "0");
    let pid = first.child.as_ref().unwrap().id();
    let started = Instant::now();
    while iceoryx2_nodes_of(pid).0 == 0 {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "node 1 never opened iceoryx2"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_millis(500));
    first.signal("KILL");
    drop(first);
    // Before: its iceoryx2 node is left behind, dead (unless another test's process, opening
    // iceoryx2 at this moment, cleaned it up already).
    let (alive, dead) = iceoryx2_nodes_of(pid);
    assert_eq!(alive, 0);
    println!("after SIGKILL: {dead} dead iceoryx2 node(s) of process {pid}");
    let recorder = Node::record("iceoryx2", &output, &out, 25, &[]);
    let second = node("node 2", "iceoryx2", &input, &output, "1");
    let source = source_bag();
    ok(
        &Node::spawn(
            "replay",
            &[
                "replay",
                source.to_str().unwrap(),
                "--transport",
                "iceoryx2",
                "--topic",
                &input,
            ],
        )
        .wait(Duration::from_secs(60)),
        "replay",
    );
    ok(&recorder.wait(Duration::from_secs(60)), "record");
    second.signal("INT");
    let log = ok(&second.wait(Duration::from_secs(30)), "node 2");
    // After: the processes that opened iceoryx2 since removed its stale resources.
    assert_eq!(iceoryx2_nodes_of(pid), (0, 0), "{log}");
    assert_eq!(recorded(&out, &output).len(), 25, "{log}");
}

/// A recorder killed while frames stream keeps a readable prefix of what a second recorder
/// (stopped cleanly at the same moment) got; the loss is bounded by the flush interval.
#[test]
fn recorder_killed_mid_stream_loses_at_most_its_flush_interval() {
    const FLUSH_S: f64 = 0.2;
    const RATE_HZ: f64 = 62.5;
    let dir = crate::tmp::tempdir().unwrap();
    let (killed_out, kept_out) = (dir.path().join("killed"), dir.path().join("kept"));
    let topic = unique_topic("rec_kill");
    let record = |name: &str, out: &Path| {
        Node::spawn(
            name,
            &[
                "record",
                "--topic",
                &topic,
                "-o",
                out.to_str().unwrap(),
                "--flush-interval",
                &FLUSH_S.to_string(),
            ],
        )
    };
    let killed = record("record (killed)", &killed_out);
    let reference = record("record (reference)", &kept_out);
    let source = source_bag();
    let _player = Node::spawn(
        "replay",
        &[
            "replay",
            source.to_str().unwrap(),
            "--topic",
            &topic,
            "--loop",
            "--wait-for-subscribers",
            "2",
        ],
    );
    let started = Instant::now();
    let count = |out: &Path| match out.join(format!("{}_0.mcap", "killed")).is_file() {
        true => raw_messages(out, Some(&topic)).len(),
        false => 0,
    };
    while count(&killed_out) < 40 {
        assert!(started.elapsed() < Duration::from_secs(30), "no frames");
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs(1));
    killed.signal("KILL");
    reference.signal("TERM");
    let _ = killed.wait(Duration::from_secs(10));
    ok(
        &reference.wait(Duration::from_secs(30)),
        "reference recorder",
    );
    let got = raw_messages(&killed_out, Some(&topic));
    let all = raw_messages(&kept_out, Some(&topic));
    assert!(!got.is_empty());
    let start = all
        .iter()
        .position(|m| *m == got[0])
        .expect("the killed recording's first frame is in the reference");
    assert!(
        all[start..].starts_with(&got),
        "the killed recording is a prefix of the reference from its first frame"
    );
    let lost = (all.len() - start - got.len()) as f64;
    let bound = RATE_HZ * (FLUSH_S + 0.15) + 2.0;
    println!(
        "recorder SIGKILL: kept {} frames, lost {lost} (bound {bound:.0})",
        got.len()
    );
    assert!(lost <= bound, "lost {lost} frames, bound {bound}");
}

#[test]
fn launch_respawns_a_killed_node() {
    let dir = crate::tmp::tempdir().unwrap();
    let file = dir.path().join("respawn.yaml");
    let topic = unique_topic("respawn");
    std::fs::write(
        &file,
        format!(
            "launch:\n  - node: {{name: recorder, exec: record, respawn: true, respawn_delay: 0.5, \
             args: [--topic, {topic}, -o, {}, --overwrite]}}\n",
            dir.path().join("rec").display()
        ),
    )
    .unwrap();
    let launch = Node::spawn("launch", &["launch", file.to_str().unwrap()]);
    let pid_of_recorder = || {
        let o = std::process::Command::new("pgrep")
            .args(["-f", &format!("minflow record --topic {topic}")])
            .output()
            .unwrap();
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .next()
            .map(|l| l.trim().to_owned())
    };
    let wait_for_pid = |not: Option<&str>| {
        let started = Instant::now();
        loop {
            match pid_of_recorder() {
                Some(pid) if Some(pid.as_str()) != not => return pid,
                _ => {}
            }
            assert!(
                started.elapsed() < Duration::from_secs(20),
                "no recorder running"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    };
    let first = wait_for_pid(None);
    std::thread::sleep(Duration::from_millis(500));
    let kill = |pid: &str| {
        assert!(std::process::Command::new("kill")
            .args(["-KILL", pid])
            .status()
            .unwrap()
            .success())
    };
    kill(&first);
    let second = wait_for_pid(Some(&first));
    std::thread::sleep(Duration::from_millis(500));
    kill(&second);
    let third = wait_for_pid(Some(&second));
    assert_ne!(third, first);
    std::thread::sleep(Duration::from_millis(500));
    launch.signal("INT");
    let o = launch.wait(Duration::from_secs(30));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.matches("respawning recorder").count(), 2, "{err}");
    assert!(
        o.status.success(),
        "the respawned recorder stopped cleanly:\n{err}"
    );
}
