//! Fixtures shared by the `data_*` tests: scenes simulated for real (12 frames of `multi`,
//! 2,500 particles, ~5 ms a frame), small synthetic frames, and bags written in the test.

#![allow(dead_code)]

use std::collections::HashMap;
use std::path::Path;
use std::sync::{Mutex, OnceLock};

use minflow::bag::BagWriter;
use minflow::msgs::{Header, ParticleFrame, Time};
use minflow::sim::{families, Family, SceneRun};

/// Ground-truth topic.
pub const TOPIC: &str = "/mpm/frames";

/// Simulated frames by (scene id, frames).
type Cache = Mutex<HashMap<(u32, u32), Vec<ParticleFrame>>>;

/// The first `frames` frames of `multi` scene `id`, simulated once per test binary.
pub fn simulate(id: u32, frames: u32) -> Vec<ParticleFrame> {
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let cache = CACHE.get_or_init(Default::default);
    if let Some(hit) = cache.lock().expect("cache").get(&(id, frames)) {
        return hit.clone();
    }
    let mut scene = families::scene(Family::Multi, id, 0);
    scene.frames = frames;
    let out: Vec<ParticleFrame> = SceneRun::new(scene)
        .expect("scene")
        .collect::<Result<_, _>>()
        .expect("simulation");
    cache
        .lock()
        .expect("cache")
        .insert((id, frames), out.clone());
    out
}

/// A synthetic frame: `n` particles with values derived from (scene, k, particle).
pub fn synthetic(scene: &str, k: u32, n: usize, material: u8) -> ParticleFrame {
    let seed = scene
        .bytes()
        .fold(7u32, |h, b| h.wrapping_mul(31).wrapping_add(u32::from(b)));
    let value = |i: usize, c: u32| {
        let h = (seed ^ (k * 7919) ^ (i as u32 * 104_729) ^ c).wrapping_mul(2_654_435_761);
        (h >> 8) as f32 / (1u32 << 24) as f32
    };
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(u64::from(k) * 16_000_000),
            frame_id: "world".into(),
        },
        scene: scene.to_owned(),
        frame_index: k,
        dt: 0.016,
        position: (0..2 * n).map(|i| value(i, 1)).collect(),
        velocity: (0..2 * n).map(|i| value(i, 2) - 0.5).collect(),
        material: vec![material; n],
    }
}

/// Writes `frames` to a new bag at `path`, all on [`TOPIC`].
pub fn write_bag<'a>(path: &Path, frames: impl IntoIterator<Item = &'a ParticleFrame>) {
    let mut writer = BagWriter::create(path).expect("create bag");
    for f in frames {
        writer.write(TOPIC, f).expect("write frame");
    }
    writer.finish().expect("finish bag");
}

/// The `[N, 4]` state (x, y, vx, vy per particle) of a message.
pub fn state_of(frame: &ParticleFrame) -> Vec<f32> {
    let mut out = Vec::with_capacity(2 * frame.position.len());
    for (p, v) in frame.position.chunks(2).zip(frame.velocity.chunks(2)) {
        out.extend_from_slice(&[p[0], p[1], v[0], v[1]]);
    }
    out
}

/// Whether two float slices are equal bit for bit.
pub fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}
