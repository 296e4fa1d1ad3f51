//! Bags that follow the format, read back exactly: frames -> bag -> frames for synthetic scenes,
//! byte-identical rewrites, the schema/channel/header records docs/design.md ("Bags") fixes, bags written by
//! mcap's own writer (no chunks, lz4, no summary, a foreign topic), bags cut at many byte
//! offsets (and one copied while its writer is still open), and `bag info`.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use mcap::records::MessageHeader;
use minflow::bag::{self, BagReader, BagWriter, ReadOutcome};
use minflow::msgs::{self, Header, ParticleFrame, Time};

const TOPIC: &str = "/mpm/frames";

/// Frame `k` of scene `s`: 2,500 particles, deterministic pseudo-random values.
fn frame(s: usize, k: u32, n: usize) -> ParticleFrame {
    let mut state = ((s as u64 + 1) * 0x9E37_79B9_7F4A_7C15) ^ u64::from(k);
    let mut next = move || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1);
        ((state >> 40) as f32) / (1u64 << 24) as f32
    };
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(u64::from(k) * 16_000_000),
            frame_id: "world".into(),
        },
        scene: format!("multi/rope+snow/{s:03}"),
        frame_index: k,
        dt: 0.016,
        position: (0..2 * n).map(|_| next()).collect(),
        velocity: (0..2 * n).map(|_| next() - 0.5).collect(),
        material: (0..n).map(|i| ((i + s) % 4) as u8).collect(),
    }
}

/// Two scenes, interleaved in stamp order, `per_scene` frames each.
fn frames(per_scene: u32) -> Vec<ParticleFrame> {
    (0..per_scene)
        .flat_map(|k| [frame(0, k, 2500), frame(1, k, 2500)])
        .collect()
}

fn write_bag(path: &Path, frames: &[ParticleFrame]) {
    let mut writer = BagWriter::create(path).expect("create");
    for f in frames {
        writer.write(TOPIC, f).expect("write");
    }
    writer.finish().expect("finish");
}

fn only_frames(outcome: &ReadOutcome) -> Vec<ParticleFrame> {
    outcome.frames.iter().map(|(_, _, f)| f.clone()).collect()
}

#[test]
fn frames_round_trip_exactly_in_order() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("a.mcap");
    let frames = frames(4);
    write_bag(&path, &frames);
    let outcome = bag::read_frames(&path, None).expect("read");
    assert_eq!(outcome.truncated, None);
    assert_eq!(outcome.skipped, 0);
    assert_eq!(only_frames(&outcome), frames);
    for ((topic, log_time, f), _) in outcome.frames.iter().zip(&frames) {
        assert_eq!(topic, TOPIC);
        assert_eq!(*log_time as i64, f.header.stamp.as_nanos());
    }
    let filtered = bag::read_frames(&path, Some(TOPIC)).expect("read topic");
    assert_eq!(only_frames(&filtered), frames);
    // The streaming form gives the same, with per-channel indexes.
    let streamed: Vec<_> = BagReader::open(&path)
        .expect("open")
        .frames()
        .collect::<Result<_, _>>()
        .expect("stream");
    assert_eq!(streamed.len(), frames.len());
    assert!(streamed
        .iter()
        .enumerate()
        .all(|(i, m)| m.index == i as u64));
}

#[test]
fn readers_can_move_between_threads() {
    fn assert_send<T: Send>() {}
    assert_send::<BagReader>();
    assert_send::<bag::Frames>();
    assert_send::<BagWriter>();
}

#[test]
fn same_frames_give_identical_bytes() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let (a, b) = (dir.path().join("a.mcap"), dir.path().join("b.mcap"));
    let frames = frames(3);
    write_bag(&a, &frames);
    write_bag(&b, &frames);
    let (a, b) = (std::fs::read(a).expect("a"), std::fs::read(b).expect("b"));
    assert!(a == b, "two writes of the same frames differ");
}

#[test]
fn records_are_what_design_md_says() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("a.mcap");
    let frames = frames(2);
    write_bag(&path, &frames);
    let bytes = std::fs::read(&path).expect("read");

    let header = mcap::read::LinearReader::new(&bytes)
        .expect("reader")
        .find_map(|r| match r {
            Ok(mcap::records::Record::Header(h)) => Some(h),
            _ => None,
        })
        .expect("header record");
    assert_eq!(header.profile, "ros2");
    assert_eq!(
        header.library,
        format!(
            "minflow/{} mcap-rust/{}",
            env!("CARGO_PKG_VERSION"),
            mcap::VERSION
        )
    );

    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("present");
    assert_eq!(summary.schemas.len(), 1);
    let schema = summary.schemas.values().next().expect("schema");
    assert_eq!(schema.name, "minflow_msgs/msg/ParticleFrame");
    assert_eq!(schema.encoding, "ros2msg");
    assert_eq!(schema.data.as_ref(), msgs::schema_text().as_bytes());
    let channel = summary.channels.values().next().expect("channel");
    assert_eq!(channel.topic, TOPIC);
    assert_eq!(channel.message_encoding, "cdr");
    let qos = &channel.metadata["offered_qos_profiles"];
    assert_eq!(qos, bag::DEFAULT_QOS_YAML);
    for line in [
        "- history: 1",
        "  depth: 10",
        "  reliability: 1",
        "  durability: 2",
    ] {
        assert!(qos.lines().any(|l| l == line), "{line} missing from {qos}");
    }
    assert!(summary
        .chunk_indexes
        .iter()
        .all(|c| c.compression == "zstd"));

    let messages: Vec<_> = mcap::MessageStream::new(&bytes)
        .expect("stream")
        .collect::<Result<_, _>>()
        .expect("messages");
    for (m, f) in messages.iter().zip(&frames) {
        assert_eq!(m.log_time as i64, f.header.stamp.as_nanos());
        assert_eq!(m.publish_time, m.log_time);
        assert_eq!(m.data.as_ref(), msgs::encode(f).as_slice());
    }
}

/// Writes `frames` with mcap's own writer and `options`, plus a `/chatter` String message after
/// each frame when `foreign` is set.
fn write_with_mcap(
    options: mcap::WriteOptions,
    frames: &[ParticleFrame],
    foreign: bool,
) -> Vec<u8> {
    let mut w = options.create(Cursor::new(Vec::new())).expect("writer");
    let schema = w
        .add_schema(msgs::TYPE_NAME, "ros2msg", msgs::schema_text().as_bytes())
        .expect("schema");
    let channel = w
        .add_channel(schema, TOPIC, "cdr", &BTreeMap::new())
        .expect("channel");
    let other_schema = w
        .add_schema("std_msgs/msg/String", "ros2msg", b"string data")
        .expect("schema");
    let other = w
        .add_channel(other_schema, "/chatter", "cdr", &BTreeMap::new())
        .expect("channel");
    for (i, f) in frames.iter().enumerate() {
        let t = f.header.stamp.as_nanos() as u64;
        let header = |channel_id| MessageHeader {
            channel_id,
            sequence: i as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header(channel), &msgs::encode(f))
            .expect("write");
        if foreign {
            let hello = [0, 1, 0, 0, 6, 0, 0, 0, b'h', b'e', b'l', b'l', b'o', 0];
            w.write_to_known_channel(&header(other), &hello)
                .expect("write");
        }
    }
    w.finish().expect("finish");
    w.into_inner().into_inner()
}

fn read_bytes(dir: &Path, name: &str, bytes: &[u8], topic: Option<&str>) -> ReadOutcome {
    let path = dir.join(name);
    std::fs::write(&path, bytes).expect("write file");
    bag::read_frames(&path, topic).expect("read")
}

#[test]
fn bags_from_other_writers_are_read() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let frames = frames(3);
    let plain = mcap::WriteOptions::new()
        .use_chunks(false)
        .compression(None);
    let lz4 = mcap::WriteOptions::new().compression(Some(mcap::Compression::Lz4));
    let bare = mcap::WriteOptions::new()
        .compression(None)
        .emit_summary_records(false)
        .emit_summary_offsets(false)
        .emit_message_indexes(false)
        .emit_chunk_indexes(false)
        .emit_statistics(false);
    for (name, options) in [("plain", plain), ("lz4", lz4), ("bare", bare)] {
        let outcome = read_bytes(
            dir.path(),
            name,
            &write_with_mcap(options, &frames, false),
            None,
        );
        assert_eq!(only_frames(&outcome), frames, "{name}");
        assert_eq!(outcome.truncated, None, "{name}");
    }
    let bytes = write_with_mcap(mcap::WriteOptions::new(), &frames, true);
    for topic in [None, Some(TOPIC)] {
        let outcome = read_bytes(dir.path(), "foreign", &bytes, topic);
        assert_eq!(only_frames(&outcome), frames);
        assert_eq!(
            outcome.skipped,
            frames.len() as u64,
            "the /chatter messages"
        );
    }
}

/// Reads a bag cut to `cut` bytes and checks it gives a prefix of `frames` plus a truncation.
fn read_cut(dir: &Path, bytes: &[u8], cut: usize, frames: &[ParticleFrame]) -> usize {
    let path: PathBuf = dir.join(format!("cut{cut}.mcap"));
    std::fs::write(&path, &bytes[..cut]).expect("write");
    let outcome = bag::read_frames(&path, None).unwrap_or_else(|e| panic!("cut {cut}: {e}"));
    let got = only_frames(&outcome);
    assert!(got.len() <= frames.len());
    assert!(got == frames[..got.len()], "cut {cut}: not a prefix");
    let t = outcome
        .truncated
        .unwrap_or_else(|| panic!("cut {cut}: no truncation reported"));
    assert_eq!(t.bytes_total, cut as u64);
    std::fs::remove_file(&path).expect("remove");
    got.len()
}

#[test]
fn truncated_bags_give_a_prefix_and_say_so() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("full.mcap");
    let frames = frames(30); // 60 frames of ~50 KB: several 1 MiB chunks
    write_bag(&path, &frames);
    let bytes = std::fs::read(&path).expect("read");
    let footer = mcap::read::footer(&bytes).expect("footer");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("present");
    let chunks = &summary.chunk_indexes;
    assert!(
        chunks.len() >= 2,
        "want several chunks, got {}",
        chunks.len()
    );
    let (first, last) = (&chunks[0], &chunks[chunks.len() - 1]);
    let data_end = (last.chunk_start_offset + last.chunk_length) as usize;
    let summary_start = footer.summary_start as usize;
    let len = bytes.len();
    let mut cuts = vec![1, 5, 8, 12, 20]; // magic, header record
    for (chunk, parts) in [(first, 8), (last, 8)] {
        let (start, length) = (
            chunk.chunk_start_offset as usize,
            chunk.chunk_length as usize,
        );
        cuts.extend((0..parts).map(|i| start + 1 + i * length / parts));
    }
    cuts.extend((1..20).map(|i| i * len / 20)); // spread over the file
    cuts.extend([
        data_end - 1,
        data_end,
        data_end + 5,
        summary_start,
        summary_start + 30,
    ]);
    cuts.extend([len - 30, len - 9, len - 8, len - 1]); // inside the footer, before end magic
    cuts.sort_unstable();
    cuts.dedup();
    assert!(cuts.len() >= 40, "{} cuts", cuts.len());
    let mut previous = 0;
    for &cut in &cuts {
        let kept = read_cut(dir.path(), &bytes, cut, &frames);
        assert!(
            kept >= previous,
            "cut {cut}: fewer frames than a shorter cut"
        );
        previous = kept;
        if cut > data_end {
            assert_eq!(
                kept,
                frames.len(),
                "cut {cut} after all messages lost frames"
            );
        }
    }
    // Cutting inside the last chunk keeps every earlier chunk's frames.
    let inside_last = last.chunk_start_offset as usize + 100;
    assert!(read_cut(dir.path(), &bytes, inside_last, &frames) >= frames.len() / 2);
    // The whole file reads without truncation.
    assert_eq!(bag::read_frames(&path, None).expect("full").truncated, None);
}

#[test]
fn bag_copied_while_its_writer_is_open_reads_as_truncated() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("live.mcap");
    let frames = frames(30);
    let mut writer = BagWriter::create(&path).expect("create");
    for f in &frames {
        writer.write(TOPIC, f).expect("write");
    }
    // What a killed writer leaves: the bytes flushed so far, the open chunk's header unpatched.
    let copy = dir.path().join("copy.mcap");
    std::fs::copy(&path, &copy).expect("copy");
    writer.finish().expect("finish");
    let outcome = bag::read_frames(&copy, None).expect("read");
    assert!(outcome.truncated.is_some());
    let got = only_frames(&outcome);
    assert!(
        !got.is_empty() && got == frames[..got.len()],
        "{} frames",
        got.len()
    );
}

#[test]
fn info_describes_the_bag() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("a.mcap");
    let frames = frames(4);
    write_bag(&path, &frames);
    let info = bag::info(&[&path]).expect("info");
    let file = &info.files[0];
    assert_eq!(file.messages, 8);
    assert_eq!(file.start_end_ns, Some((0, 3 * 16_000_000)));
    assert_eq!(file.topics.len(), 1);
    assert_eq!(file.topics[0].type_name, msgs::TYPE_NAME);
    assert_eq!(file.topics[0].count, 8);
    assert_eq!(file.scenes.len(), 2);
    assert_eq!(file.particle_counts, BTreeMap::from([(2500, 8)]));
    assert_eq!(file.materials().iter().sum::<u64>(), 5000);
    let text = info.to_string();
    for needle in [
        TOPIC,
        msgs::TYPE_NAME,
        "cdr",
        "multi/rope+snow/001 (4 frames, 2500 particles)",
        "2500",
    ] {
        assert!(text.contains(needle), "{needle} missing from:\n{text}");
    }
    assert!(bag::check(&[path]).expect("check").is_ok());
}
