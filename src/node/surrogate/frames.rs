//! Particle frames as the surrogate node handles them: a frame's `[N, 4]` rows as the model
//! takes them ([`state_rows`], from `msgs`), the frame a prediction makes ([`predicted_frame`],
//! its arrays by [`crate::msgs::split_rows`]) and a payload's size ([`payload_bytes`]).

use crate::msgs::{split_rows, ParticleFrame, Time};

/// Interleaved position/velocity -> `[N, 4]` rows (x, y, vx, vy), as `Surrogate::step` takes
/// them: [`crate::msgs::state_rows`].
pub use crate::msgs::state_rows;

/// The size of a payload in bytes, as it travelled (CDR) or as its arrays take in memory.
pub(super) fn payload_bytes(payload: &crate::transport::Payload) -> usize {
    use crate::transport::Payload;
    match payload {
        Payload::Cdr(bytes) => bytes.len(),
        Payload::Frame(f) => {
            4 * (f.position.len() + f.velocity.len()) + f.material.len() + f.scene.len()
        }
        Payload::Malformed(_) => 0,
    }
}

/// The frame `steps` frames after `input`, carrying `rows` (`[N, 4]`).
pub(super) fn predicted_frame(input: &ParticleFrame, rows: &[f32], steps: u32) -> ParticleFrame {
    let (position, velocity) = split_rows(rows);
    let stamp_ns = input.header.stamp.as_nanos()
        + (f64::from(input.dt) * 1e9).round() as i64 * i64::from(steps);
    let mut header = input.header.clone();
    header.stamp = Time::from_nanos(stamp_ns.max(0) as u64);
    ParticleFrame {
        header,
        scene: input.scene.clone(),
        frame_index: input.frame_index + steps,
        dt: input.dt,
        position,
        velocity,
        material: input.material.clone(),
    }
}
