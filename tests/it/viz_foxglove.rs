//! The live view in Foxglove (issue 17) seen by a real client of the protocol:
//! `minflow replay --foxglove 127.0.0.1:0` on the bundled bag, and
//! `tests/python/foxglove_client.py` (Python `websockets`, subprotocol `foxglove.sdk.v1`: the
//! Foxglove SDK's name for the protocol once called `foxglove.websocket.v1`) subscribes to `<topic>/points` and decodes every message with
//! Foxglove's published protobuf schemas (`foxglove-schemas-protobuf`). Each of the bag's
//! frames must arrive as a `foxglove.PointCloud` of N points (N = the bag's particle count)
//! whose first point has the frame's first position and its material's colour.
//! The interpreter: [`crate::python_support::interpreter`].

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::Command;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crate::python_support::{interpreter, INSTALL_HINT};
use crate::transport_support::{ok, source_bag, unique_topic, Node};
use minflow::bag::{bag_paths, BagReader, FRAMES_TOPIC};
use minflow::msgs::{self, ParticleFrame};
use minflow::viz::cloud::{material_colour, POINT_STRIDE};
use serde_json::Value;

/// The frames of `bag` on [`FRAMES_TOPIC`], in file order.
fn frames(bag: &Path) -> Vec<ParticleFrame> {
    let mut out = Vec::new();
    for path in bag_paths(&[bag.to_path_buf()]).unwrap() {
        for m in BagReader::open(&path).unwrap() {
            let m = m.unwrap();
            if m.topic() == FRAMES_TOPIC {
                out.push(msgs::decode(&m.data).unwrap());
            }
        }
    }
    out
}

/// Waits (at most 60 s) for a line starting with `prefix` on `stream` and returns the rest of
/// that line; a thread collects everything the stream says, returned by the handle.
fn wait_for_line(
    stream: impl Read + Send + 'static,
    prefix: &str,
    what: &str,
) -> (String, std::thread::JoinHandle<String>) {
    let (tx, rx) = mpsc::channel();
    let all = std::thread::spawn(move || {
        let mut all = String::new();
        for line in BufReader::new(stream).lines().map_while(Result::ok) {
            let _ = tx.send(line.clone());
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    while let Ok(line) = rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
        if let Some(rest) = line.strip_prefix(prefix) {
            return (rest.trim().to_owned(), all);
        }
    }
    panic!("{what} never said {prefix:?}:\n{}", all.join().unwrap());
}

/// The URL `node` serves Foxglove on (its `foxglove: serving on ws://...` line).
fn served_url(node: &Node) -> String {
    node.wait_for_stderr_line("foxglove: serving on ", Duration::from_secs(60))
}

/// Runs the Python client against `url`: `count` messages of `topic`, as JSON.
fn client(url: &str, topic: &str, count: usize) -> Value {
    let python = interpreter();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/foxglove_client.py");
    let output = Command::new(&python)
        .arg(&script)
        .args([url, topic, &count.to_string(), "60"])
        .output()
        .unwrap_or_else(|e| panic!("cannot run {python}: {e}"));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.code() != Some(3),
        "Python packages missing for {python}; run `{INSTALL_HINT}`\n{stderr}"
    );
    assert!(
        output.status.success(),
        "foxglove_client.py failed:\n{stderr}"
    );
    serde_json::from_slice(&output.stdout).expect("the client prints JSON")
}

#[test]
fn replay_serves_every_frame_as_a_point_cloud_to_a_foxglove_client() {
    let bag = source_bag();
    let want = frames(&bag);
    assert_eq!(want.len(), 25);
    let n = want[0].len();
    assert!(n > 100, "{n} particles");
    let topic = unique_topic("viz");
    // The Foxglove client is the one subscriber replay waits for.
    let player = Node::spawn(
        "replay",
        &[
            "replay",
            bag.to_str().unwrap(),
            "--topic",
            &topic,
            "--foxglove",
            "127.0.0.1:0",
            "--wait-for-subscribers",
            "1",
            "--wait-timeout",
            "60",
        ],
    );
    let url = served_url(&player);
    let points = format!("{topic}/points");
    let got = client(&url, &points, want.len());
    assert_eq!(got["subprotocol"], "foxglove.sdk.v1");
    let channel = &got["channel"];
    assert_eq!(channel["topic"], points.as_str());
    assert_eq!(channel["schemaName"], "foxglove.PointCloud");
    assert_eq!(channel["encoding"], "protobuf");
    assert_eq!(channel["schemaEncoding"], "protobuf");
    let seen = got["frames"].as_array().unwrap();
    assert_eq!(seen.len(), want.len());
    for (k, (cloud, frame)) in seen.iter().zip(&want).enumerate() {
        assert_eq!(cloud["points"].as_u64(), Some(n as u64), "frame {k}");
        assert_eq!(
            cloud["bytes"].as_u64(),
            Some(n as u64 * u64::from(POINT_STRIDE))
        );
        assert_eq!(cloud["frame_id"], "world");
        let stamp = frame.header.stamp.as_unsigned_nanos().unwrap();
        assert_eq!(cloud["stamp_ns"].as_u64(), Some(stamp), "frame {k}");
        let first: Vec<f64> = serde_json::from_value(cloud["first"].clone()).unwrap();
        assert_eq!(first[0] as f32, frame.position[0], "x of frame {k}");
        assert_eq!(first[1] as f32, frame.position[1], "y of frame {k}");
        let colour = material_colour(frame.material[0]).map(f64::from);
        assert_eq!(&first[3..7], &colour, "colour of frame {k}");
        assert_eq!(first[7], f64::from(frame.material[0]));
    }
    let out = player.wait(Duration::from_secs(60));
    let log = ok(&out, "replay");
    assert!(log.contains("replay: 25 frame(s)"), "{log}");
}

#[test]
fn bad_foxglove_addresses_are_usage_errors() {
    let bag = source_bag();
    for (args, what) in [
        (
            vec!["replay", bag.to_str().unwrap(), "--foxglove", ":8765"],
            "no host",
        ),
        (
            vec!["replay", bag.to_str().unwrap(), "--foxglove", "h:99999"],
            "port",
        ),
        (
            vec!["simulate", "--foxglove", "127.0.0.1:0"],
            "without --publish",
        ),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_minflow"))
            .args(&args)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{what}: {out:?}");
    }
}

#[test]
fn record_points_writes_clouds_foxglove_reads_from_the_bag() {
    let bag = source_bag();
    let want = frames(&bag);
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("rec");
    let topic = unique_topic("vizrec");
    let recorder = Node::spawn(
        "record",
        &[
            "record",
            "--topic",
            &topic,
            "-o",
            out.to_str().unwrap(),
            "--count",
            "25",
            "--points",
        ],
    );
    let player = Node::spawn(
        "replay",
        &["replay", bag.to_str().unwrap(), "--topic", &topic],
    );
    ok(&player.wait(Duration::from_secs(90)), "replay");
    ok(&recorder.wait(Duration::from_secs(30)), "record");
    let python = interpreter();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/read_points.py");
    let output = Command::new(&python)
        .arg(&script)
        .args(bag_paths(&[out]).unwrap())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "read_points.py failed:\n{stderr}");
    let got: Value = serde_json::from_slice(&output.stdout).unwrap();
    let points = &got[format!("{topic}/points")];
    assert_eq!(points["schema_encoding"], "protobuf", "{got}");
    assert_eq!(points["message_encoding"], "protobuf");
    let messages = points["messages"].as_array().unwrap();
    assert_eq!(messages.len(), want.len());
    for (m, frame) in messages.iter().zip(&want) {
        assert_eq!(m["points"].as_u64(), Some(frame.len() as u64));
        assert_eq!(
            m["log_time"].as_u64(),
            frame.header.stamp.as_unsigned_nanos()
        );
    }
}

#[test]
fn node_colours_its_predictions_by_their_error_against_the_truth() {
    let bag = source_bag();
    let n = frames(&bag)[0].len();
    let input = unique_topic("vizin");
    let output = unique_topic("vizout");
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/all-grid-mingru-small");
    let node = Node::spawn(
        "node",
        &[
            "node",
            "--model",
            model.to_str().unwrap(),
            "--in",
            &input,
            "--out",
            &output,
            "--status",
            "none",
            "--foxglove",
            "127.0.0.1:0",
            // Every frame predicted even when the test machine is busy (the replay plays at
            // the bag's rate; at the default depth, 8, a slow step under load drops frames).
            "--queue-depth",
            "64",
        ],
    );
    let url = served_url(&node);
    // The client subscribes before the first frame is played.
    let python = interpreter();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/foxglove_client.py");
    let mut client = Command::new(&python)
        .arg(&script)
        .args([&url, &format!("{output}/points"), "20", "90"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let client_err = client.stderr.take().unwrap();
    let (_, client_err) = wait_for_line(client_err, "subscribed", "foxglove_client.py");
    let player = Node::spawn(
        "replay",
        &["replay", bag.to_str().unwrap(), "--topic", &input],
    );
    ok(&player.wait(Duration::from_secs(90)), "replay");
    let out = client.wait_with_output().unwrap();
    let stderr = client_err.join().unwrap();
    assert!(out.status.success(), "foxglove_client.py failed:\n{stderr}");
    let got: Value = serde_json::from_slice(&out.stdout).unwrap();
    let seen = got["frames"].as_array().unwrap();
    assert_eq!(seen.len(), 20);
    let mut errors = Vec::new();
    for cloud in seen {
        assert_eq!(cloud["points"].as_u64(), Some(n as u64));
        let first: Vec<f64> = serde_json::from_value(cloud["first"].clone()).unwrap();
        let error = first[2] as f32;
        assert!((0.0..0.1).contains(&error), "error {error}");
        let colour = minflow::viz::cloud::error_colour(error).map(f64::from);
        assert_eq!(&first[3..7], &colour, "coloured by error, not material");
        errors.push(error);
    }
    assert!(errors.iter().any(|&e| e > 0.0), "{errors:?}");
}
