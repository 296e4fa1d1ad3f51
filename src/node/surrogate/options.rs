//! How a surrogate node runs ([`NodeOptions`], [`OnGap`]) and what it reports
//! ([`NodeReport`], [`summary`]).

use std::time::Duration;

use crate::msgs::status::SurrogateStatus;

/// What to do with a frame that does not follow the previous one of its scene
/// (`node --on-gap`, `cli::node`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
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
    /// Pipelined calls: a live batch's predictions are read back and projected on the
    /// lander thread while the loop gathers and records the next batch's call, so a GPU
    /// runs while the host works (`batcher.rs`, `lander.rs`).
    pub pipeline: bool,
    /// Before a batch size first carries frames of a particle count: one call of it
    /// (`Surrogate::warm_up_batches`; the sizes follow the scenes seen, up to `max_batch`), so
    /// no burst meets an unready shape (`warm.rs`).
    pub warm_up: bool,
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
