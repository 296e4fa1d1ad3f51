//! What the surrogate node counts and logs: the run's counters ([`Tally`], the
//! [`NodeReport`] published as status), the sizes of its batched calls ([`BatchStats`]),
//! where its loop's wall time went ([`StageTimes`]), each (scene, reason) logged once, the
//! start line, the latency percentiles at the end and the wall-clock stamp of each report.
//! Used by `node_loop.rs` and `run.rs` (`minflow node`).

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::model::store::{StepTimes, Surrogate};
use crate::msgs::Time;
use crate::ops::NetOps;
use crate::transport::Transport;

use super::options::{NodeOptions, NodeReport};

/// The run's counters, and which (scene, reason kind) pairs were already logged.
pub(super) struct Tally {
    pub(super) report: NodeReport,
    pub(super) logged: HashSet<(String, String)>,
}

impl Tally {
    /// Records `reason` as the last error; logs it once per scene and reason kind (the
    /// reason's text up to its first digit).
    pub(super) fn note(&mut self, scene: &str, reason: String) {
        let kind: String = reason
            .split(|c: char| c.is_ascii_digit())
            .next()
            .unwrap_or("")
            .to_owned();
        if self.logged.insert((scene.to_owned(), kind)) {
            tracing::warn!(
                "{}: scene {scene:?}: {reason} (logged once per scene and reason)",
                self.report.node
            );
        }
        self.report.last_error = format!("{scene}: {reason}");
    }
}

/// Scenes per network call (dynamic batching), as the status reports them.
#[derive(Debug, Default)]
pub(super) struct BatchStats {
    calls: u64,
    scenes: u64,
    max: u32,
}

impl BatchStats {
    /// Records the calls of one batch: scenes per call.
    pub(super) fn record(&mut self, calls: &[usize]) {
        for &c in calls {
            self.calls += 1;
            self.scenes += c as u64;
            self.max = self.max.max(c as u32);
        }
    }

    /// Writes the totals into `report`.
    pub(super) fn fill(&self, report: &mut NodeReport) {
        report.calls = self.calls;
        report.batched = self.scenes;
        report.batch_max = self.max;
    }

    /// The totals as one log line.
    pub(super) fn line(&self) -> String {
        let mean = self.scenes as f64 / self.calls.max(1) as f64;
        format!(
            "calls={} batch_mean={mean:.2} batch_max={}",
            self.calls, self.max
        )
    }
}

/// The loop's stages in [`StageTimes::line`]'s order, `other` last (`bench node` reads them
/// back).
pub const LOOP_STAGES: [&str; 8] = [
    "wait", "intake", "stack", "call", "split", "publish", "landing", "other",
];

/// Where the node's loop spent its wall time since it subscribed, by stage (the closing
/// log line; `bench node` reads it): blocked on the transport with nothing due, taking
/// decoded samples in (count, queue: `intake.rs`), the model's calls by
/// [`StepTimes`] stage, publishing predictions (encode, send), waiting for the lander thread
/// to hand a pipelined call back, and the rest (choosing the
/// batch, building jobs and predicted frames, rollouts' bookkeeping, status); beside them,
/// the decoder thread's busy time (decode and check) and the lander thread's (`--pipeline`).
#[derive(Debug)]
pub(super) struct StageTimes {
    since: Instant,
    /// The decoder thread's busy time, ns (beside the loop, not part of its wall time).
    pub(super) decode: Arc<AtomicU64>,
    /// The lander thread's busy time, ns (`--pipeline`: landing, projecting and publishing
    /// the calls; beside the loop, as `decode`).
    pub(super) land: Arc<AtomicU64>,
    pub(super) wait: Duration,
    pub(super) intake: Duration,
    pub(super) step: StepTimes,
    pub(super) publish: Duration,
    /// Blocked on the lander thread for a pipelined call to come back (`--pipeline`).
    pub(super) landing: Duration,
}

impl StageTimes {
    /// Zero times, the wall clock counted from now.
    pub(super) fn new() -> Self {
        StageTimes {
            since: Instant::now(),
            decode: Arc::default(),
            land: Arc::default(),
            wait: Duration::ZERO,
            intake: Duration::ZERO,
            step: StepTimes::default(),
            publish: Duration::ZERO,
            landing: Duration::ZERO,
        }
    }

    /// The times as one log line of `name=seconds` pairs, the loop's wall time counted up
    /// to `end`, `other_s` the part of it no stage holds, `decode_s` the decoder thread's and
    /// `land_s` the lander thread's.
    pub(super) fn line(&self, end: Instant) -> String {
        let wall = end - self.since;
        let staged = [
            self.wait,
            self.intake,
            self.step.stack,
            self.step.call,
            self.step.split,
            self.publish,
            self.landing,
        ];
        let other = wall.saturating_sub(staged.iter().sum());
        let fields: Vec<String> = LOOP_STAGES
            .iter()
            .zip(staged.iter().chain([&other]))
            .map(|(n, d)| format!("{n}_s={:.3}", d.as_secs_f64()))
            .collect();
        let decode = self.decode.load(Ordering::Relaxed) as f64 / 1e9;
        let land = self.land.load(Ordering::Relaxed) as f64 / 1e9;
        format!(
            "time: wall_s={:.3} {} decode_s={decode:.3} land_s={land:.3}",
            wall.as_secs_f64(),
            fields.join(" ")
        )
    }
}

/// Logs the model and topics the node serves, once at start.
pub(super) fn log_start<B: NetOps>(
    options: &NodeOptions,
    surrogate: &Surrogate<B>,
    transport: &dyn Transport,
) {
    let meta = surrogate.meta();
    tracing::info!(
        "{}: {} architecture, {} core, T = {}, {} -> {} over {}{}",
        options.name,
        meta.arch_name(),
        meta.core_name(),
        meta.window().max(1),
        options.input,
        options.output,
        transport.kind(),
        options
            .rollout
            .map_or(String::new(), |k| format!(", closed loop {k} frames"))
    );
    tracing::info!(
        "{}: dynamic batching: up to {} scene(s) a call, waiting up to {:.1} ms",
        options.name,
        options.max_batch,
        options.max_batch_delay.as_secs_f64() * 1e3
    );
}

/// Logs the arrival -> publication latency percentiles (nothing when no frame was timed).
pub(super) fn log_latencies(name: &str, latencies_us: &mut [f64]) {
    if latencies_us.is_empty() {
        return;
    }
    latencies_us.sort_by(f64::total_cmp);
    let pct = |p: f64| latencies_us[((latencies_us.len() - 1) as f64 * p).round() as usize];
    tracing::info!(
        "{}: arrival -> publication latency over {} frames: p50 {:.0} us, p99 {:.0} us, max {:.0} us",
        name,
        latencies_us.len(),
        pct(0.5),
        pct(0.99),
        pct(1.0)
    );
}

/// Now, as a message stamp (ns since the Unix epoch; 0 before it).
pub(super) fn wall_time() -> Time {
    Time::from_nanos(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64),
    )
}
