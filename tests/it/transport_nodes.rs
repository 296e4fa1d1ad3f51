//! Replay -> record over every transport, as separate `minflow` processes on loopback: the
//! recorded bag holds exactly the source bag's frames (bytes of every message, order,
//! count). Plus the issue's transport-specific checks: a late zenoh subscriber, a zenoh peer
//! configured from a file (explicit endpoints, multicast scouting off), an iceoryx2
//! publisher killed with SIGKILL and started again, the recorder killed with SIGKILL and
//! SIGTERM, malformed payloads counted without stopping the recorder, and a second recorder
//! on the same folder refused. A clean run logs no ERROR and no colour codes into a pipe.

use std::time::Duration;

use crate::transport_support::*;
use minflow::bag::FRAMES_TOPIC;

const SOURCE_FRAMES: usize = 25;

/// replay (source bag, --topic T) -> record (--topic T --count 25); the recording equals
/// the source message for message.
fn roundtrip(transport: &str, extra_record: &[&str], extra_replay: &[&str]) {
    roundtrip_of(
        &source_bag(),
        SOURCE_FRAMES,
        transport,
        extra_record,
        extra_replay,
    );
}

/// [`roundtrip`] of the `frames` frames of bag `source`.
fn roundtrip_of(
    source: &std::path::Path,
    frames: usize,
    transport: &str,
    extra_record: &[&str],
    extra_replay: &[&str],
) {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("rec");
    let topic = unique_topic(transport);
    let mut rec_args = vec![
        "record",
        "--transport",
        transport,
        "--topic",
        &topic,
        "-o",
        out.to_str().unwrap(),
    ];
    let count = frames.to_string();
    rec_args.extend_from_slice(&["--count", &count]);
    rec_args.extend_from_slice(extra_record);
    let env = domain_env(transport, 4);
    let recorder = Node::spawn_env("record", &rec_args, &env);
    let mut play_args = vec![
        "replay",
        source.to_str().unwrap(),
        "--transport",
        transport,
        "--topic",
        &topic,
    ];
    play_args.extend_from_slice(extra_replay);
    let player = Node::spawn_env("replay", &play_args, &env);
    let play_err = ok(&player.wait(Duration::from_secs(90)), "replay");
    // A recorder short of its 25 frames says so with both logs' tails (what the replay saw
    // of its subscribers, what the recorder matched), not the recorder's discovery chatter.
    let rec = recorder
        .wait_or_kill(Duration::from_secs(30))
        .unwrap_or_else(|out| {
            panic!(
                "{transport} record did not get {frames} frames within 30 s\n\
                 replay:\n{}\nrecord:\n{}",
                log_tail(play_err.as_bytes()),
                log_tail(&out.stderr)
            )
        });
    let rec_err = ok(&rec, "record");
    let want = raw_messages(source, Some(FRAMES_TOPIC));
    assert_eq!(want.len(), frames);
    let got = raw_messages(&out, Some(&topic));
    assert_eq!(
        got.len(),
        want.len(),
        "frames recorded\nreplay: {play_err}\nrecord: {rec_err}"
    );
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            g == w,
            "message {i} differs ({} vs {} bytes)",
            g.len(),
            w.len()
        );
    }
    assert!(out.join("metadata.yaml").is_file());
    assert_eq!(counter(&rec_err, "malformed"), Some(0));
    // A clean run logs no ERROR (the DDS transport used to log "Cannot remove Writer ...
    // Disconnected" on every shutdown), and a log read through a pipe has no colour codes.
    for (what, log) in [("replay", &play_err), ("record", &rec_err)] {
        assert!(!log.contains("ERROR"), "{transport} {what}:\n{log}");
        assert!(
            !log.contains('\x1b'),
            "{transport} {what}: colour codes\n{log}"
        );
    }
}

#[test]
fn zenoh_replay_record_roundtrip() {
    roundtrip("zenoh", &[], &[]);
}

#[test]
fn iceoryx2_replay_record_roundtrip() {
    roundtrip("iceoryx2", &[], &[]);
}

/// Frames of 40,000 particles (about 800 kB of CDR each: a `multi` liquid scene with `simulate --grid 256`, docs/mpm.md) cross
/// zenoh, iceoryx2 and ROS 2 whole: the recording equals the source message for message.
#[test]
fn frames_of_40000_particles_cross_every_transport() {
    let dir = crate::tmp::tempdir().unwrap();
    let bag = scene_of_40000(dir.path(), 4, 3);
    let (_, _, first) = minflow::bag::read_frames(&bag, None)
        .unwrap()
        .frames
        .remove(0);
    assert_eq!(first.len(), 40_000);
    for transport in ["zenoh", "iceoryx2"] {
        roundtrip_of(&bag, 3, transport, &[], &[]);
    }
    roundtrip_of(&bag, 3, "ros2", &[], &["--rate", "0.25"]);
}

/// At a quarter of real time: the recorder's DDS reader keeps the last 10 frames (the ROS 2
/// default QoS), so a recorder starved for 160 ms by the tests running beside it on 2 cores
/// loses a frame at full rate (seen under load); the round trip is what this checks.
#[test]
fn ros2_replay_record_roundtrip() {
    roundtrip("ros2", &[], &["--rate", "0.25"]);
}

#[test]
fn zenoh_peers_from_config_files_without_multicast() {
    let dir = crate::tmp::tempdir().unwrap();
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let listen = dir.path().join("listen.json5");
    let connect = dir.path().join("connect.json5");
    std::fs::write(
        &listen,
        format!(
            r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }},
                 scouting: {{ multicast: {{ enabled: false }}, gossip: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    std::fs::write(
        &connect,
        format!(
            r#"{{ mode: "peer", connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }},
                 listen: {{ endpoints: [] }},
                 scouting: {{ multicast: {{ enabled: false }}, gossip: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    roundtrip(
        "zenoh",
        &["--zenoh-config", listen.to_str().unwrap()],
        &["--zenoh-config", connect.to_str().unwrap()],
    );
}

#[test]
fn zenoh_late_subscriber_gets_frames_published_after_it_joined() {
    let dir = crate::tmp::tempdir().unwrap();
    let topic = unique_topic("late");
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
            "0",
        ],
    );
    std::thread::sleep(Duration::from_secs(2));
    let out = dir.path().join("late");
    let recorder = Node::spawn(
        "record",
        &[
            "record",
            "--topic",
            &topic,
            "-o",
            out.to_str().unwrap(),
            "--count",
            "30",
        ],
    );
    ok(&recorder.wait(Duration::from_secs(60)), "record");
    let frames: Vec<_> = raw_messages(&out, Some(&topic))
        .iter()
        .map(|b| minflow::msgs::decode(b).unwrap())
        .collect();
    assert_eq!(frames.len(), 30);
    // Consecutive frames of the looping bag, from wherever the subscriber joined.
    for w in frames.windows(2) {
        assert_eq!(
            w[1].frame_index,
            (w[0].frame_index + 1) % SOURCE_FRAMES as u32,
            "no frame lost after joining"
        );
    }
}

#[test]
fn iceoryx2_publisher_killed_then_restarted_serves_a_new_subscriber() {
    let topic = unique_topic("iox_kill");
    let source = source_bag();
    let play = |name: &str| {
        Node::spawn(
            name,
            &[
                "replay",
                source.to_str().unwrap(),
                "--transport",
                "iceoryx2",
                "--topic",
                &topic,
                "--loop",
                "--wait-for-subscribers",
                "0",
            ],
        )
    };
    let first = play("replay 1");
    std::thread::sleep(Duration::from_secs(1));
    first.signal("KILL");
    drop(first);
    let _second = play("replay 2");
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("after_kill");
    let recorder = Node::record("iceoryx2", &topic, &out, 10, &[]);
    ok(
        &recorder.wait(Duration::from_secs(60)),
        "record after a killed publisher",
    );
    assert_eq!(raw_messages(&out, Some(&topic)).len(), 10);
}

/// Replays the 25 source frames into a recorder that is then stopped by `signal`; returns the
/// output folder (kept alive by the returned TempDir) and the recorder's stderr.
fn record_then_signal(signal: &str) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("rec");
    let topic = unique_topic(&signal.to_lowercase());
    let recorder = Node::spawn(
        "record",
        &[
            "record",
            "--topic",
            &topic,
            "-o",
            out.to_str().unwrap(),
            "--flush-interval",
            "0.2",
        ],
    );
    let source = source_bag();
    let player = Node::spawn(
        "replay",
        &["replay", source.to_str().unwrap(), "--topic", &topic],
    );
    ok(&player.wait(Duration::from_secs(60)), "replay");
    std::thread::sleep(Duration::from_secs(1));
    recorder.signal(signal);
    let _ = recorder.wait(Duration::from_secs(30));
    (dir, out)
}

#[test]
fn recorder_killed_leaves_a_bag_readable_up_to_its_last_chunk() {
    let (_dir, out) = record_then_signal("KILL");
    // Every frame arrived more than one flush interval before the kill.
    let outcome = minflow::data::load(std::slice::from_ref(&out), None);
    let (trajs, _report) = outcome.expect("a killed recording loads for training");
    assert_eq!(trajs.iter().map(|t| t.frames).sum::<usize>(), SOURCE_FRAMES);
    let info = Node::spawn("bag info", &["bag", "info", out.to_str().unwrap()])
        .wait(Duration::from_secs(30));
    // Exit 3: read, but cut (no summary or footer).
    assert_eq!(
        info.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&info.stderr)
    );
    assert!(String::from_utf8_lossy(&info.stdout).contains("25"));
}

#[test]
fn recorder_terminated_leaves_a_complete_bag() {
    let (_dir, out) = record_then_signal("TERM");
    let check = Node::spawn("bag check", &["bag", "check", out.to_str().unwrap()])
        .wait(Duration::from_secs(30));
    ok(&check, "bag check");
    assert_eq!(raw_messages(&out, None).len(), SOURCE_FRAMES);
}

#[test]
fn malformed_zenoh_payloads_are_counted_and_recording_goes_on() {
    use minflow::transport::{self, Transport};
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("rec");
    let topic = unique_topic("malformed");
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
        ],
    );
    // A raw zenoh publisher on the same key sends three bad payloads first.
    let session = transport::zenoh::ZenohTransport::open(None).unwrap();
    let key = topic.trim_start_matches('/').to_owned();
    let raw = {
        use zenoh::Wait;
        session.session().declare_publisher(key).wait().unwrap()
    };
    let mut frames = session.publisher(&topic).unwrap();
    assert!(transport::wait_for_subscribers(
        frames.as_ref(),
        1,
        Duration::from_secs(30)
    ));
    std::thread::sleep(Duration::from_millis(500));
    let good = raw_messages(&source_bag(), Some(FRAMES_TOPIC));
    let mut wrong_len = minflow::msgs::decode(&good[0]).unwrap();
    wrong_len.velocity.pop();
    let bad: Vec<Vec<u8>> = vec![
        (0..997u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8)
            .collect(),
        good[0][..good[0].len() / 2].to_vec(),
        minflow::msgs::encode(&wrong_len),
    ];
    {
        use zenoh::Wait;
        for b in &bad {
            raw.put(b.clone()).wait().unwrap();
        }
    }
    for bytes in &good {
        let frame = minflow::msgs::decode(bytes).unwrap();
        frames.publish_cdr(bytes, &frame).unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    let stderr = ok(&recorder.wait(Duration::from_secs(60)), "record");
    assert_eq!(counter(&stderr, "malformed"), Some(3), "{stderr}");
    assert_eq!(raw_messages(&out, Some(&topic)), good);
}

/// Issue 16: a second recorder on a folder a recorder is writing exits 1 naming the holder,
/// with or without `--overwrite`, and the first one's bag keeps every frame.
#[test]
fn a_second_recorder_on_the_same_folder_is_refused() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("rec");
    let topic = unique_topic("lock");
    let args = |extra: &'static [&'static str]| {
        let mut a = vec!["record", "--topic", &topic, "-o", out.to_str().unwrap()];
        a.extend_from_slice(extra);
        a.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let first_args = args(&["--flush-interval", "0.2"]);
    let first = Node::spawn(
        "record",
        &first_args.iter().map(String::as_str).collect::<Vec<_>>(),
    );
    let lock = out.join(minflow::node::record::LOCK_FILE);
    let started = std::time::Instant::now();
    while std::fs::read_to_string(&lock).map_or(true, |s| s.is_empty()) {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "the first recorder never took the lock"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    for extra in [&[][..], &["--overwrite"][..]] {
        let second_args = args(extra);
        let second = Node::spawn(
            "record2",
            &second_args.iter().map(String::as_str).collect::<Vec<_>>(),
        )
        .wait(Duration::from_secs(30));
        let stderr = String::from_utf8_lossy(&second.stderr);
        assert_eq!(second.status.code(), Some(1), "{extra:?}: {stderr}");
        let holder = format!("(process {})", first.child.as_ref().unwrap().id());
        assert!(
            stderr.contains("another recorder is writing here") && stderr.contains(&holder),
            "{stderr}"
        );
    }
    let player = Node::spawn(
        "replay",
        &["replay", source_bag().to_str().unwrap(), "--topic", &topic],
    );
    ok(&player.wait(Duration::from_secs(60)), "replay");
    std::thread::sleep(Duration::from_secs(1));
    first.signal("TERM");
    let _ = first.wait(Duration::from_secs(30));
    assert_eq!(raw_messages(&out, Some(&topic)).len(), SOURCE_FRAMES);
}
