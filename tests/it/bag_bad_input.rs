//! Bags that are wrong in one way each: a foreign schema on the requested topic, frames whose
//! arrays disagree, NaN positions, undecodable CDR, random bytes, an empty file, corrupted
//! bytes. Each gives an error (never a panic) whose text names the file, the topic and the
//! message index where they apply; `bag check` finds frame-index gaps and changed particle
//! counts; `bag_paths` expands folders.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use mcap::records::MessageHeader;
use minflow::bag::{self, BagError, BagWriter, ReadOptions};
use minflow::msgs::{self, Header, ParticleFrame, Time};

const TOPIC: &str = "/mpm/frames";

fn frame(scene: &str, k: u32, n: usize) -> ParticleFrame {
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(u64::from(k) * 16_000_000),
            frame_id: "world".into(),
        },
        scene: scene.into(),
        frame_index: k,
        dt: 0.016,
        position: (0..2 * n).map(|i| i as f32 / (2 * n) as f32).collect(),
        velocity: vec![0.25; 2 * n],
        material: (0..n).map(|i| (i % 4) as u8).collect(),
    }
}

/// Writes CDR payloads on `TOPIC` with `BagWriter::write_raw` (no validation).
fn write_raw_bag(path: &Path, payloads: &[Vec<u8>]) {
    let mut w = BagWriter::create(path).expect("create");
    for (k, p) in payloads.iter().enumerate() {
        w.write_raw(TOPIC, k as u64 * 16_000_000, p).expect("write");
    }
    w.finish().expect("finish");
}

/// Asserts the error text names the file, the topic and (when given) the message index.
fn assert_names(err: &BagError, path: &Path, index: Option<u64>) {
    let text = err.to_string();
    assert!(
        text.contains(&path.display().to_string()),
        "no path in: {text}"
    );
    assert!(text.contains(TOPIC), "no topic in: {text}");
    if let Some(i) = index {
        assert!(
            text.contains(&format!("message {i}")),
            "no index in: {text}"
        );
    }
}

#[test]
fn foreign_schema_on_the_requested_topic_is_an_error() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("foreign.mcap");
    let mut w = mcap::Writer::new(Cursor::new(Vec::new())).expect("writer");
    let schema = w
        .add_schema("other_msgs/msg/Thing", "ros2msg", b"int32 x")
        .expect("schema");
    let channel = w
        .add_channel(schema, TOPIC, "cdr", &BTreeMap::new())
        .expect("channel");
    let header = MessageHeader {
        channel_id: channel,
        sequence: 0,
        log_time: 0,
        publish_time: 0,
    };
    w.write_to_known_channel(&header, &[0, 1, 0, 0, 7, 0, 0, 0])
        .expect("write");
    w.finish().expect("finish");
    std::fs::write(&path, w.into_inner().into_inner()).expect("file");

    let err = bag::read_frames(&path, Some(TOPIC)).unwrap_err();
    assert!(matches!(err, BagError::ForeignSchema { .. }), "{err}");
    assert_names(&err, &path, None);
    assert!(err.to_string().contains("other_msgs/msg/Thing"), "{err}");
    // Not asked for by topic: skipped and counted.
    let outcome = bag::read_frames(&path, None).expect("read");
    assert_eq!((outcome.frames.len(), outcome.skipped), (0, 1));
}

#[test]
fn bad_frames_name_file_topic_and_index() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let good: Vec<Vec<u8>> = (0..2).map(|k| msgs::encode(&frame("s", k, 10))).collect();
    let mut mismatched = frame("s", 2, 10);
    mismatched.velocity.truncate(17); // 2N = 20 expected
    let mut nan = frame("s", 2, 10);
    nan.position[5] = f32::NAN;
    let mut cut = msgs::encode(&frame("s", 2, 10));
    cut.truncate(50);
    let cases = [
        (
            "lengths",
            msgs::encode(&mismatched),
            "velocity has 17 values, expected 20",
        ),
        ("nan", msgs::encode(&nan), "position[5] is NaN"),
        ("cdr", cut, "CDR: "),
    ];
    for (name, bad, needle) in cases {
        let path = dir.path().join(format!("{name}.mcap"));
        let payloads = [good.clone(), vec![bad, good[0].clone()]].concat();
        write_raw_bag(&path, &payloads);
        let err = bag::read_frames(&path, None).unwrap_err();
        assert!(err.is_message_error(), "{name}: {err}");
        assert_names(&err, &path, Some(2));
        assert!(err.to_string().contains(needle), "{name}: {err}");
        // Lenient reading counts and skips it.
        let options = ReadOptions {
            topic: None,
            lenient: true,
        };
        let outcome = bag::read_frames_with(&path, &options).expect("lenient");
        assert_eq!((outcome.frames.len(), outcome.invalid), (3, 1), "{name}");
    }
}

#[test]
fn writer_rejects_invalid_frames() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("w.mcap");
    let mut w = BagWriter::create(&path).expect("create");
    w.write(TOPIC, &frame("s", 0, 4)).expect("valid frame");
    let mut nan = frame("s", 1, 4);
    nan.velocity[0] = f32::INFINITY;
    let err = w.write(TOPIC, &nan).unwrap_err();
    assert_names(&err, &path, Some(1));
    w.finish().expect("finish");
}

#[test]
fn random_bytes_and_empty_files_are_not_bags() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let empty = dir.path().join("empty.mcap");
    std::fs::write(&empty, b"").expect("write");
    let err = bag::read_frames(&empty, None).unwrap_err();
    assert!(
        matches!(err, BagError::NotMcap { .. }) && err.to_string().contains("empty"),
        "{err}"
    );
    assert!(err.to_string().contains(&empty.display().to_string()));

    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut random = |n: usize| -> Vec<u8> {
        (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            })
            .collect()
    };
    let noise = dir.path().join("noise.mcap");
    std::fs::write(&noise, random(10_000)).expect("write");
    let err = bag::read_frames(&noise, None).unwrap_err();
    assert!(matches!(err, BagError::NotMcap { .. }), "{err}");
    assert!(err.to_string().contains(&noise.display().to_string()));
    assert!(bag::info(&[&noise]).is_err());

    // Noise after a valid magic, and a real bag with random bytes overwritten: never a panic.
    let good = dir.path().join("good.mcap");
    let frames: Vec<_> = (0..6).map(|k| frame("s", k, 500)).collect();
    let mut w = BagWriter::create(&good).expect("create");
    frames
        .iter()
        .for_each(|f| w.write(TOPIC, f).expect("write"));
    w.finish().expect("finish");
    let bytes = std::fs::read(&good).expect("read");
    for round in 0..200 {
        let mut bad = if round == 0 {
            [mcap::MAGIC, &random(5000)].concat()
        } else {
            bytes.clone()
        };
        let spots = random(8);
        for pair in spots.chunks(2) {
            let at = (usize::from(pair[0]) << 8 | usize::from(pair[1])) * 31 % bad.len();
            bad[at] = random(1)[0];
        }
        let path = dir.path().join("bad.mcap");
        std::fs::write(&path, &bad).expect("write");
        if let Ok(outcome) = bag::read_frames(&path, None) {
            // Chunk CRCs are checked before a chunk's messages are used, so what survives is
            // frames as written, in order, none twice (damaged chunks are skipped).
            let got: Vec<_> = outcome.frames.into_iter().map(|(_, _, f)| f).collect();
            let mut rest = frames.iter();
            assert!(got.iter().all(|g| rest.any(|f| f == g)), "round {round}");
        }
        let _ = bag::info(&[&path]);
        let _ = bag::check(&[path]);
    }
}

#[test]
fn check_finds_gaps_and_changed_particle_counts() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("seq.mcap");
    let mut w = BagWriter::create(&path).expect("create");
    for k in [0, 1, 3] {
        w.write(TOPIC, &frame("gappy", k, 8)).expect("write");
    }
    for (k, n) in [(0, 8), (1, 8), (2, 9)] {
        w.write(TOPIC, &frame("growing", k, n)).expect("write");
    }
    w.finish().expect("finish");
    let report = bag::check(&[&path]).expect("check");
    assert!(!report.is_ok());
    assert_eq!((report.messages, report.scenes), (6, 2));
    let text = report.to_string();
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.contains("\"gappy\"") && p.contains("gap")),
        "{text}"
    );
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.contains("particle count changed from 8 to 9")),
        "{text}"
    );
    assert_eq!(report.problem_count, 2, "{text}");

    // A foreign schema on /mpm/frames and a changed dt are problems too.
    let other = dir.path().join("other.mcap");
    let mut w = mcap::Writer::new(Cursor::new(Vec::new())).expect("writer");
    let schema = w
        .add_schema("other_msgs/msg/Thing", "ros2msg", b"int32 x")
        .expect("schema");
    let channel = w
        .add_channel(schema, TOPIC, "cdr", &BTreeMap::new())
        .expect("channel");
    let header = MessageHeader {
        channel_id: channel,
        sequence: 0,
        log_time: 0,
        publish_time: 0,
    };
    w.write_to_known_channel(&header, &[0, 1, 0, 0, 7, 0, 0, 0])
        .expect("write");
    w.finish().expect("finish");
    std::fs::write(&other, w.into_inner().into_inner()).expect("file");
    let report = bag::check(&[&other]).expect("check");
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.contains("other_msgs/msg/Thing")),
        "{report}"
    );
    let dt = dir.path().join("dt.mcap");
    let mut w = BagWriter::create(&dt).expect("create");
    for k in 0..3 {
        let mut f = frame("dt", k, 4);
        f.dt = if k == 2 { 0.032 } else { 0.016 };
        w.write(TOPIC, &f).expect("write");
    }
    w.finish().expect("finish");
    let report = bag::check(&[&dt]).expect("check");
    assert_eq!(report.problem_count, 1, "{report}");
    assert!(
        report.problems[0].contains("dt changed from 0.016 to 0.032"),
        "{report}"
    );
}

/// `bag check` compares schemas as parsed definitions: one that differs from `msgs/*.msg`
/// only in comments, blank lines and spacing (as other writers lay it out, e.g. the Python
/// mcap-ros2 writer) passes; a changed field type is a problem naming the field.
#[test]
fn check_compares_parsed_schema_definitions() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let write = |name: &str, schema: &str| {
        let path = dir.path().join(name);
        let mut w = mcap::Writer::new(Cursor::new(Vec::new())).expect("writer");
        let id = w
            .add_schema(msgs::TYPE_NAME, "ros2msg", schema.as_bytes())
            .expect("schema");
        let channel = w
            .add_channel(id, TOPIC, "cdr", &BTreeMap::new())
            .expect("channel");
        for k in 0..3u32 {
            let header = MessageHeader {
                channel_id: channel,
                sequence: k,
                log_time: u64::from(k) * 16_000_000,
                publish_time: u64::from(k) * 16_000_000,
            };
            w.write_to_known_channel(&header, &msgs::encode(&frame("s", k, 8)))
                .expect("write");
        }
        w.finish().expect("finish");
        std::fs::write(&path, w.into_inner().into_inner()).expect("file");
        path
    };
    let ours = msgs::schema_text();
    let relaid: String = ours
        .lines()
        .map(|l| match l.starts_with('=') || l.starts_with("MSG:") {
            true => format!("{l}\n"),
            false => format!("  {}   # another comment\n\n", l.replace(' ', "  ")),
        })
        .collect();
    assert_ne!(relaid, ours);
    let report = bag::check(&[write("relaid.mcap", &relaid)]).expect("check");
    assert!(report.is_ok(), "{report}");
    let changed = ours.replacen("float32[] position", "float64[] position", 1);
    let report = bag::check(&[write("changed.mcap", &changed)]).expect("check");
    assert!(
        report.problems.iter().any(|p| p.contains("schema differs")
            && p.contains("\"float64[] position\" where \"float32[] position\" was expected")),
        "{report}"
    );
}

#[test]
fn bag_paths_expands_folders_sorted() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    for name in ["b.mcap", "a.mcap", "notes.txt"] {
        std::fs::write(dir.path().join(name), b"").expect("write");
    }
    let paths = bag::bag_paths(&[dir.path().to_path_buf()]).expect("paths");
    let names: Vec<_> = paths
        .iter()
        .filter_map(|p| p.file_name()?.to_str())
        .collect();
    assert_eq!(names, ["a.mcap", "b.mcap"]);
    let missing = bag::bag_paths(&[PathBuf::from("/no/such/bags")]).unwrap_err();
    assert!(missing.to_string().contains("/no/such/bags"), "{missing}");
    let empty = crate::tmp::tempdir().expect("tempdir");
    let none = bag::bag_paths(&[empty.path().to_path_buf()]).unwrap_err();
    assert!(matches!(none, BagError::NoBags { .. }), "{none}");
}

/// Issue 16: `replay` of a bag whose log times are not sorted in file order (the first
/// message logged 1 s after the others) plays every frame without `--start-offset`, and with
/// `--start-offset 0.5` drops exactly the frames logged in the first half second after the
/// earliest log time.
#[test]
fn replay_filters_by_offset_from_the_earliest_log_time_only() {
    let dir = crate::tmp::tempdir().unwrap();
    let path = dir.path().join("unsorted.mcap");
    let mut w = BagWriter::create(&path).expect("create");
    w.write_raw(TOPIC, 1_000_000_000, &msgs::encode(&frame("s", 0, 10)))
        .expect("write");
    for k in 1..40u32 {
        let log = u64::from(k) * 16_000_000;
        w.write_raw(TOPIC, log, &msgs::encode(&frame("s", k, 10)))
            .expect("write");
    }
    w.finish().expect("finish");
    let replay = |extra: &[&str]| {
        let mut args = vec![
            "replay",
            path.to_str().unwrap(),
            "--rate",
            "0",
            "--wait-for-subscribers",
            "0",
            "--topic",
            "/minflow_test/unsorted",
        ];
        args.extend_from_slice(extra);
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_minflow"))
            .args(&args)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
        assert_eq!(o.status.code(), Some(0), "{extra:?}: {stderr}");
        stderr
    };
    let all = replay(&[]);
    assert!(
        all.contains("replay: 40 frame(s)") && all.contains("(0 filtered)"),
        "{all}"
    );
    // Log times 16 ms .. 624 ms and 1 s; at least 0.5 s after the earliest (16 ms), i.e. at
    // 516 ms or later: k = 33..39 (528 ms on) and the 1 s frame, 8 frames; 32 filtered.
    let late = replay(&["--start-offset", "0.5"]);
    assert!(
        late.contains("replay: 8 frame(s)") && late.contains("(32 filtered)"),
        "{late}"
    );
}

/// A bag written one frame per chunk with one byte flipped inside any one chunk's compressed
/// data: the damaged chunk is skipped, the 23 intact frames before and after it are read, and
/// the truncation counts one skipped chunk (as `mcap recover` reads around damage).
#[test]
fn a_damaged_chunk_is_skipped_and_the_rest_is_read() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let good = dir.path().join("good.mcap");
    let frames: Vec<_> = (0..24).map(|k| frame("s", k, 200)).collect();
    let mut w = BagWriter::create(&good).expect("create");
    for f in &frames {
        w.write(TOPIC, f).expect("write");
        w.flush().expect("flush");
    }
    w.finish().expect("finish");
    let bytes = std::fs::read(&good).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("has summary");
    assert_eq!(summary.chunk_indexes.len(), 24);
    for (k, chunk) in summary.chunk_indexes.iter().enumerate() {
        let mut bad = bytes.clone();
        // The middle of the chunk record's compressed records.
        let at = (chunk.chunk_start_offset + chunk.chunk_length / 2 + 20) as usize;
        bad[at] ^= 0x5a;
        let path = dir.path().join(format!("bad{k}.mcap"));
        std::fs::write(&path, &bad).expect("write");
        let outcome = bag::read_frames(&path, None).expect("read");
        let got: Vec<_> = outcome.frames.into_iter().map(|(_, _, f)| f).collect();
        let mut want = frames.clone();
        want.remove(k);
        assert_eq!(got.len(), 23, "chunk {k}");
        assert!(got == want, "chunk {k}: frames differ");
        let t = outcome.truncated.expect("damage is reported");
        assert_eq!(
            (t.chunks_skipped, t.messages_read),
            (1, k as u64),
            "chunk {k}"
        );
        assert_eq!(t.messages_after, 23 - k as u64, "chunk {k}");
        assert!(t.to_string().contains("skipped 1 damaged chunk"), "{t}");
    }
}

/// `bag check` reads the summary and message indexes too: a valid bag is OK; one flipped byte
/// anywhere in the summary (covered by the footer's CRC), a message index record cut short or
/// pointing outside its chunk, or statistics that miscount are problems, while every frame
/// still reads.
#[test]
fn check_finds_a_damaged_summary_or_message_index() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let good = dir.path().join("good.mcap");
    let frames: Vec<_> = (0..8).map(|k| frame("s", k, 100)).collect();
    let mut w = BagWriter::create(&good).expect("create");
    for f in &frames {
        w.write(TOPIC, f).expect("write");
        w.flush().expect("flush");
    }
    w.finish().expect("finish");
    let report = bag::check(&[&good]).expect("check");
    assert!(report.is_ok(), "{report}");
    let bytes = std::fs::read(&good).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("has summary");
    let footer = mcap::read::footer(&bytes).expect("footer");
    let crc_end = bytes.len() - 8 - 4;
    // `summary`: the damage is past the data section, so reading must not report lost data.
    let check_damaged = |bad: &[u8], what: &str, summary: bool| {
        let path = dir.path().join("bad.mcap");
        std::fs::write(&path, bad).expect("write");
        let report = bag::check(&[&path]).expect("check");
        assert!(!report.is_ok(), "{what}: check said OK");
        assert!(report.to_string().contains("bad.mcap"), "{report}");
        let read = bag::read_frames(&path, None).expect("read");
        assert_eq!(read.frames.len(), frames.len(), "{what}: frames lost");
        if let (true, Some(t)) = (summary, &read.truncated) {
            panic!("{what}: a damaged summary reported as lost data: {t}");
        }
    };
    for at in (footer.summary_start as usize..crc_end).step_by(7) {
        let mut bad = bytes.clone();
        bad[at] ^= 0x10;
        check_damaged(&bad, &format!("summary byte {at}"), true);
    }
    for (k, chunk) in summary.chunk_indexes.iter().enumerate() {
        let index_at = (chunk.chunk_start_offset + chunk.chunk_length) as usize;
        // The record's length (cut short), then the first entry's offset (its high byte).
        for (at, what) in [
            (index_at + 1, "length"),
            (index_at + 9 + 2 + 4 + 8 + 7, "offset"),
        ] {
            let mut bad = bytes.clone();
            bad[at] ^= 0x40;
            check_damaged(&bad, &format!("chunk {k} message index {what}"), false);
        }
    }
}
