//! Property tests of bag reading under damage (proptest): a bag of 1-12 frames in 1-4 frame
//! chunks, then cut at any length, one byte flipped anywhere, or one chunk record's length
//! overwritten. Reading never panics; what it returns is frames as written, in order, none
//! twice; a cut keeps every frame of the chunks before it; a flip or a bad length loses at most
//! the frames of one chunk (the rest is read through the summary's chunk index); only a
//! damaged magic makes the file unreadable. No loss is silent: whenever a frame is missing the
//! outcome reports the damage (what makes `bag info`, `replay`, `train` and `eval` exit 3).

use std::path::Path;

use minflow::bag::{self, BagWriter};
use minflow::msgs::{Header, ParticleFrame, Time};
use proptest::prelude::*;

const TOPIC: &str = "/mpm/frames";

fn frame(k: u32) -> ParticleFrame {
    let n = 20 + k as usize;
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(u64::from(k) * 16_000_000),
            frame_id: "world".into(),
        },
        scene: "p".into(),
        frame_index: k,
        dt: 0.016,
        position: (0..2 * n)
            .map(|i| (i as f32 * 0.37 + k as f32) % 1.0)
            .collect(),
        velocity: (0..2 * n).map(|i| i as f32 * 0.01 - k as f32).collect(),
        material: (0..n).map(|i| (i % 4) as u8).collect(),
    }
}

/// Writes `count` frames, closing a chunk after every `per_chunk`; returns the bytes, the
/// frames and each chunk's (start, end, frames in it).
fn bag_bytes(
    dir: &Path,
    count: u32,
    per_chunk: u32,
) -> (Vec<u8>, Vec<ParticleFrame>, Vec<(u64, u64)>) {
    let path = dir.join("good.mcap");
    let frames: Vec<_> = (0..count).map(frame).collect();
    let mut w = BagWriter::create(&path).expect("create");
    for (k, f) in frames.iter().enumerate() {
        w.write(TOPIC, f).expect("write");
        if (k as u32 + 1).is_multiple_of(per_chunk) {
            w.flush().expect("flush");
        }
    }
    w.finish().expect("finish");
    let bytes = std::fs::read(&path).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("present");
    let mut chunks: Vec<_> = summary
        .chunk_indexes
        .iter()
        .map(|c| (c.chunk_start_offset, c.chunk_start_offset + c.chunk_length))
        .collect();
    chunks.sort();
    (bytes, frames, chunks)
}

/// Reads `bytes` as a bag: Err when unreadable, else the frames in file order. Frames lost
/// (fewer than `written`) without the damage being reported fail the test: no silent loss.
fn read(dir: &Path, bytes: &[u8], written: usize) -> Result<Vec<ParticleFrame>, String> {
    let path = dir.join("damaged.mcap");
    std::fs::write(&path, bytes).expect("write");
    // Info and check must not panic either.
    let _ = bag::info(&[&path]);
    let _ = bag::check(&[&path]);
    let outcome = bag::read_frames(&path, None).map_err(|e| e.to_string())?;
    let frames: Vec<_> = outcome.frames.into_iter().map(|(_, _, f)| f).collect();
    assert!(
        frames.len() == written || outcome.truncated.is_some(),
        "{} of {written} frames read and no damage reported",
        frames.len()
    );
    Ok(frames)
}

/// Whether `got` is `all` with some frames left out, in order, none twice.
fn in_order(got: &[ParticleFrame], all: &[ParticleFrame]) -> bool {
    let mut rest = all.iter();
    got.iter().all(|g| rest.any(|f| f == g))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn a_cut_keeps_every_chunk_before_it(count in 1u32..12, per_chunk in 1u32..4, cut in any::<prop::sample::Index>()) {
        let dir = crate::tmp::tempdir().expect("tempdir");
        let (bytes, frames, chunks) = bag_bytes(dir.path(), count, per_chunk);
        let len = cut.index(bytes.len());
        match read(dir.path(), &bytes[..len], frames.len()) {
            Err(e) => prop_assert!(len < 8, "cut at {len}: {e}"),
            Ok(got) => {
                let whole = chunks.iter().filter(|c| c.1 <= len as u64).count();
                let kept = (whole as u32 * per_chunk).min(count) as usize;
                prop_assert!(got.len() >= kept, "cut at {len}: {} of {kept}", got.len());
                prop_assert!(got[..] == frames[..got.len()], "cut at {len}: not a prefix");
            }
        }
    }

    #[test]
    fn a_flipped_byte_loses_at_most_one_chunk(count in 1u32..12, per_chunk in 1u32..4, at in any::<prop::sample::Index>(), mask in 1u8..=255) {
        let dir = crate::tmp::tempdir().expect("tempdir");
        let (mut bytes, frames, _) = bag_bytes(dir.path(), count, per_chunk);
        let at = at.index(bytes.len());
        bytes[at] ^= mask;
        match read(dir.path(), &bytes, frames.len()) {
            Err(e) => prop_assert!(at < 8, "flip at {at}: {e}"),
            Ok(got) => {
                prop_assert!(in_order(&got, &frames), "flip at {at}: frames out of order");
                let lost = frames.len() - got.len();
                prop_assert!(lost <= per_chunk as usize, "flip at {at}: {lost} frames lost");
            }
        }
    }

    #[test]
    fn a_bad_chunk_length_loses_at_most_one_chunk(count in 1u32..12, per_chunk in 1u32..4, which in any::<prop::sample::Index>(), length in any::<u64>()) {
        let dir = crate::tmp::tempdir().expect("tempdir");
        let (mut bytes, frames, chunks) = bag_bytes(dir.path(), count, per_chunk);
        let (start, _) = chunks[which.index(chunks.len())];
        let at = start as usize + 1;
        bytes[at..at + 8].copy_from_slice(&length.to_le_bytes());
        let got = read(dir.path(), &bytes, frames.len()).map_err(TestCaseError::fail)?;
        prop_assert!(in_order(&got, &frames), "frames out of order");
        prop_assert!(frames.len() - got.len() <= per_chunk as usize, "{} frames lost", frames.len() - got.len());
    }
}

/// Every chunk's opcode byte damaged, one at a time, with masks that make it unknown (skipped
/// by MCAP readers, as the specification says) or another record type: the chunk's frames
/// are lost and the loss is reported (the statistics' count gives it away), the rest is read.
#[test]
fn a_damaged_chunk_opcode_is_reported() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let (bytes, frames, chunks) = bag_bytes(dir.path(), 10, 1);
    for &(start, _) in &chunks {
        for mask in [0x10, 0x80, 0xff, 0x01] {
            let mut damaged = bytes.clone();
            damaged[start as usize] ^= mask;
            let got = read(dir.path(), &damaged, frames.len())
                .unwrap_or_else(|e| panic!("chunk at {start}, mask {mask:#x}: {e}"));
            assert!(in_order(&got, &frames), "chunk at {start}: out of order");
            assert!(
                got.len() + 1 >= frames.len(),
                "chunk at {start}: {} read",
                got.len()
            );
        }
    }
    // Where the loss was: the damaged chunk's offset, the frames before and after it.
    for (k, &(start, _)) in chunks.iter().enumerate().skip(1) {
        let mut damaged = bytes.clone();
        damaged[start as usize] ^= 0x10;
        let path = dir.path().join("damaged.mcap");
        std::fs::write(&path, &damaged).expect("write");
        let t = bag::read_frames(&path, None)
            .expect("read")
            .truncated
            .expect("damage is reported");
        let k = k as u64;
        assert_eq!(
            (
                t.bytes_read,
                t.messages_read,
                t.messages_after,
                t.chunks_skipped
            ),
            (start, k, 9 - k, 1),
            "chunk {k}: {t}"
        );
        assert!(
            t.found_at_end && t.to_string().contains("skipped 1 damaged chunk"),
            "{t}"
        );
    }
}

/// A chunk whose length field was damaged to reach into the summary section: the reader fails
/// past the Data End record, where damage usually means only the summary is hurt, but here a
/// chunk was lost, and the summary's message count (its CRC intact) says so.
#[test]
fn a_chunk_length_reaching_into_the_summary_is_reported() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let (bytes, frames, chunks) = bag_bytes(dir.path(), 6, 1);
    let footer = mcap::read::footer(&bytes).expect("footer");
    for &(start, _) in &chunks {
        let mut damaged = bytes.clone();
        let length = footer.summary_start + 20 - start - 9;
        damaged[start as usize + 1..start as usize + 9].copy_from_slice(&length.to_le_bytes());
        let got = read(dir.path(), &damaged, frames.len()).expect("readable");
        assert!(in_order(&got, &frames), "chunk at {start}: out of order");
    }
}
