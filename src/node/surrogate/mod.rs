//! The surrogate node (`minflow node`): subscribes to particle frames, keeps one hidden
//! state per `scene`, and for every input frame publishes the predicted next frame
//! (docs/design.md, "Messages": same scene and material, `frame_index` + 1, stamp + `dt`).
//! In closed loop (`rollout` R), after the first T frames of a scene it publishes R predicted
//! frames by feeding its own predictions back, one network call at a time between the
//! other scenes' work. A bundled grid model (`train --bundle K`)
//! predicts K frames per network call there, so R frames cost ceil(R / K) calls, each from
//! the last frame of the call before. Fed live frames, a bundled model makes one call per
//! input frame and publishes the first frame of its bundle (the next frame, as a
//! single-frame model does); the rest of the bundle is not published, since the next input
//! frame supersedes it.
//!
//! Threads: the transport's I/O thread only hands samples over (a channel); this node's
//! own thread decodes, checks, queues per scene and predicts, so a slow model never blocks
//! a publisher. When frames of a scene arrive faster than they are predicted, the oldest
//! pending frame of that scene is dropped and counted (`queue_depth`).
//!
//! State rules: a scene's hidden state is reset when the scene starts (frame_index 0 or an
//! unseen scene id), on a gap or out-of-order frame ([`OnGap::Reset`]; [`OnGap::Skip`]
//! drops out-of-order frames and carries on over gaps), and after `idle_timeout` without
//! activity (a frame arriving, or a prediction of its rollout published); states idle that
//! long are dropped; in closed loop a scene is rolled out once (until its frame 0 comes
//! again), even if its state was dropped meanwhile, and at most `max_scenes` are kept (least
//! recently seen evicted), so memory stays bounded. A grid model with `--reference
//! first-frame` takes the first frame of a scene as its reference positions and keeps them
//! over a gap reset (the stream goes on), not over a restart.
//!
//! Bad input is never predicted on: a payload larger than `max_frame_bytes` is `rejected`
//! before it is decoded; a payload that does not decode is `malformed`; a frame with a
//! particle count other than the model's N, non-finite values or an unknown material id is
//! `rejected`. Each is counted, logged once per scene and reason, and reported in
//! [`SurrogateStatus`] (published once per second); other scenes are served as usual.
//!
//! Dynamic batching (`max_batch`, `max_batch_delay`; [`batcher`]): frames of different
//! scenes that wait together go through one network call, each scene's state stacked into
//! the call's batch and split back, as NVIDIA Triton Inference Server's dynamic batcher
//! does for requests. Closed-loop rollouts ([`closed`]) are calls like any other, so a long
//! rollout never holds the other scenes up. Sharding (`shard`; [`shard`]): nodes of one
//! group divide the scenes among the live ones over zenoh liveliness.
//!
//! Files: [`admission`] holds the rules (which frames are taken, what a frame does to its
//! scene's state), [`scenes`] the per-scene states under those rules, [`intake`] the
//! arrival of frames, [`batcher`] the calls, [`closed`] the rollouts, [`shard`] the group,
//! [`run`] the loop, [`report`] the counters and logs. This file holds the options and the
//! frame helpers.

mod admission;
mod batcher;
mod closed;
mod intake;
mod report;
mod run;
mod scenes;
pub mod shard;

use std::time::Duration;

use crate::msgs::status::SurrogateStatus;
use crate::msgs::{ParticleFrame, Time};

pub use report::LOOP_STAGES;
pub use run::run;

/// What to do with a frame that does not follow the previous one of its scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum OnGap {
    /// Reset the scene's hidden state and start again from this frame.
    Reset,
    /// Drop frames older than the last one; carry the state over forward gaps.
    Skip,
}

/// How the node runs.
#[derive(Debug, Clone)]
pub struct NodeOptions {
    /// Node name (in logs and status reports).
    pub name: String,
    /// Input topic (ground-truth frames).
    pub input: String,
    /// Output topic (predicted frames).
    pub output: String,
    /// Status topic; None for no status reports.
    pub status: Option<String>,
    /// Gap policy.
    pub on_gap: OnGap,
    /// Reset and drop a scene's state after this long without frames.
    pub idle_timeout: Duration,
    /// Most scene states kept at once.
    pub max_scenes: usize,
    /// Pending frames per scene before the oldest is dropped.
    pub queue_depth: usize,
    /// Payloads larger than this (bytes) are rejected before decoding (`--max-frame-bytes`).
    pub max_frame_bytes: usize,
    /// Closed loop: after the first T frames of a scene, publish K predicted frames.
    pub rollout: Option<usize>,
    /// Closed-loop pacing: predicted frames per simulated second times this factor
    /// (1 = the scene's own pace); 0 = as fast as possible.
    pub rate: f64,
    /// Dynamic batching: most scenes stepped by one network call (1: one scene a call).
    pub max_batch: usize,
    /// Dynamic batching: how long the oldest waiting frame may wait for others to join
    /// its call (Triton's `max_queue_delay_microseconds`).
    pub max_batch_delay: Duration,
    /// Sharding over zenoh: the group whose live nodes divide the scenes among them.
    pub shard: Option<String>,
    /// Stop after this many predicted frames were published (tests, benchmarks).
    pub max_published: Option<u64>,
    /// Log the counters as one line this often.
    pub stats_interval: Option<Duration>,
    /// Subscribe to the input only once the output has this many subscribers (so a
    /// recorder started alongside misses nothing).
    pub wait_for_subscribers: usize,
    /// Live view (`--foxglove`): the input on `<input>/points`, predictions on
    /// `<output>/points` coloured by their error against the ground truth.
    pub foxglove: Option<crate::viz::LiveView>,
}

/// Totals of a node run, as in the status message.
pub type NodeReport = SurrogateStatus;

/// Interleaved position/velocity -> `[N, 4]` rows (x, y, vx, vy), as `Surrogate::step` takes them.
pub fn state_rows(frame: &ParticleFrame) -> Vec<f32> {
    let mut rows = Vec::with_capacity(frame.len() * 4);
    for i in 0..frame.len() {
        rows.extend_from_slice(&[
            frame.position[2 * i],
            frame.position[2 * i + 1],
            frame.velocity[2 * i],
            frame.velocity[2 * i + 1],
        ]);
    }
    rows
}

/// The size of a payload in bytes, as it travelled (CDR) or as its arrays take in memory.
fn payload_bytes(payload: &crate::transport::Payload) -> usize {
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
fn predicted_frame(input: &ParticleFrame, rows: &[f32], steps: u32) -> ParticleFrame {
    let n = rows.len() / 4;
    let mut position = Vec::with_capacity(2 * n);
    let mut velocity = Vec::with_capacity(2 * n);
    for r in rows.chunks_exact(4) {
        position.extend_from_slice(&r[..2]);
        velocity.extend_from_slice(&r[2..]);
    }
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

/// The counters as one line.
pub fn summary(r: &NodeReport) -> String {
    format!(
        "{}: received={} predicted={} published={} dropped={} malformed={} rejected={} scenes={} \
         calls={} batch_mean={:.2} batch_max={}{}",
        r.node,
        r.received,
        r.predicted,
        r.published,
        r.dropped,
        r.malformed,
        r.rejected,
        r.active_scenes,
        r.calls,
        r.batch_mean(),
        r.batch_max,
        if r.last_error.is_empty() {
            String::new()
        } else {
            format!("; last error: {}", r.last_error)
        }
    )
}
