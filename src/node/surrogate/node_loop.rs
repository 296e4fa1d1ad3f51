//! The surrogate node's state between iterations of its loop ([`NodeLoop`]): the model and
//! the publishers, the per-scene states ([`Scenes`]), the queues ([`Schedule`]), counters,
//! the shard group and the timers of the periodic reports; and what the loop does with them
//! apart from taking frames in (`intake.rs`) and stepping batches (`batcher.rs`): status
//! and counters once a second, publishing predicted frames, the closing reports.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::model::store::Surrogate;
use crate::msgs::ParticleFrame;
use crate::ops::NetOps;
use crate::transport::{FramePublisher, StatusPublisher};
use crate::viz::PredictionView;

use super::flight::{lock, Published, SharedPublisher};
use super::lander::Lander;
use super::options::{summary, NodeOptions, NodeReport};
use super::report::{log_latencies, wall_time, BatchStats, StageTimes, Tally};
use super::scenes::Scenes;
use super::schedule::Schedule;
use super::shard::Shard;

/// The node's state between loop iterations: per-scene hidden states, pending frames,
/// rollouts under way, counters and the timers of the periodic reports.
pub(super) struct NodeLoop<'a, B: NetOps> {
    pub(super) options: &'a NodeOptions,
    pub(super) surrogate: &'a Surrogate<B>,
    publisher: SharedPublisher,
    status_pub: Option<Box<dyn StatusPublisher>>,
    /// The model's particle count, where it has a fixed one.
    pub(super) model_n: Option<usize>,
    /// Frames a scene needs before closed loop starts (T, at least 1).
    pub(super) window: usize,
    pub(super) tally: Tally,
    pub(super) scenes: Scenes<B>,
    /// The frames and rollout calls waiting for the network.
    pub(super) schedule: Schedule<B>,
    pub(super) batches: BatchStats,
    /// Where the loop's wall time went.
    pub(super) times: StageTimes,
    /// The shard group (`--shard`), and the counts of frames of other nodes' scenes and of
    /// scenes this node took over.
    pub(super) shard: Option<Shard>,
    pub(super) others: u64,
    pub(super) adopted: u64,
    pub(super) next_status: Instant,
    next_stats: Option<Instant>,
    /// Arrival -> publication latencies, us: the last [`LATENCY_WINDOW`] to 2x that many.
    latencies_us: Vec<f64>,
    pub(super) view: Option<PredictionView>,
    /// Scene states dropped so far.
    pub(super) evicted: Evictions,
    /// The lander thread of the pipelined calls (`--pipeline`; `lander.rs`).
    pub(super) lander: Option<Lander<B>>,
    /// What the batch warm-up did per kind of call: particle count, closed loop or not
    /// (`--warm-up-batches`; `warm.rs`).
    pub(super) warmed: HashMap<(usize, bool), Warmed>,
}

/// What the node has warmed up of one kind of call (particle count, closed loop or not;
/// `warm.rs`).
#[derive(Debug, Default)]
pub(super) struct Warmed {
    /// Scenes seen with calls of this kind (at most `--max-batch` of them kept).
    pub(super) scenes: HashSet<String>,
    /// The largest batch size warmed up (0: none).
    pub(super) up_to: usize,
}

/// Scene states a node dropped.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Evictions {
    /// At `max_scenes`: the least recently active scene made room for a new one.
    pub(super) full: u64,
    /// Idle past `idle_timeout`.
    pub(super) idle: u64,
}

/// Latencies kept for the percentiles logged at exit (bounded memory over hours).
const LATENCY_WINDOW: usize = 100_000;

impl<'a, B: NetOps> NodeLoop<'a, B> {
    /// An empty loop state for the node.
    pub(super) fn new(
        options: &'a NodeOptions,
        surrogate: &'a Surrogate<B>,
        publisher: Box<dyn FramePublisher>,
        status_pub: Option<Box<dyn StatusPublisher>>,
    ) -> Self {
        let meta = surrogate.meta();
        NodeLoop {
            options,
            surrogate,
            publisher: Arc::new(Mutex::new(publisher)),
            status_pub,
            model_n: meta.fixed_particles(),
            window: meta.window().max(1),
            tally: Tally {
                report: NodeReport {
                    node: options.name.clone(),
                    ..NodeReport::default()
                },
                logged: HashSet::new(),
            },
            scenes: Scenes::new(),
            schedule: Schedule::new(),
            batches: BatchStats::default(),
            times: StageTimes::new(),
            shard: None,
            others: 0,
            adopted: 0,
            next_status: Instant::now(),
            next_stats: options.stats_interval.map(|d| Instant::now() + d),
            latencies_us: Vec::new(),
            evicted: Evictions::default(),
            lander: None,
            warmed: HashMap::new(),
            view: options
                .foxglove
                .as_ref()
                .map(|v| PredictionView::new(v, &options.input, &options.output)),
        }
    }

    /// True once `max_published` frames were published.
    pub(super) fn done(&self) -> bool {
        self.options
            .max_published
            .is_some_and(|m| self.tally.report.published >= m)
    }

    /// Once per second: publishes the status, drops idle scenes and frees the batches most
    /// of whose scenes have moved on ([`super::scenes::Scenes::compact`]). Every
    /// `stats_interval`: logs the counters.
    pub(super) fn periodic(&mut self) {
        if Instant::now() >= self.next_status {
            self.next_status += Duration::from_secs(1);
            self.stamp_report();
            if let Some(p) = self.status_pub.as_mut() {
                if let Err(e) = p.publish(&self.tally.report) {
                    tracing::warn!("status: {e}");
                }
            }
            let idle = self.scenes.evict_idle(self.options.idle_timeout);
            self.note_idle(idle as u64);
            self.scenes.compact();
        }
        if let (Some(due), Some(every)) = (self.next_stats, self.options.stats_interval) {
            if Instant::now() >= due {
                self.next_stats = Some(due + every);
                tracing::info!("{}", summary(&self.tally.report));
            }
        }
    }

    /// Counts and logs `idle` scene states dropped as idle past `--idle-timeout`.
    pub(super) fn note_idle(&mut self, idle: u64) {
        if idle > 0 {
            self.evicted.idle += idle;
            tracing::info!(
                "{}: {idle} scene state(s) idle over --idle-timeout dropped ({} so far)",
                self.options.name,
                self.evicted.idle
            );
        }
    }

    /// Sets the report's scene count, batch sizes and stamp to now.
    fn stamp_report(&mut self) {
        self.tally.report.active_scenes = self.scenes.len() as u32;
        self.batches.fill(&mut self.tally.report);
        self.tally.report.stamp = wall_time();
    }

    /// Publishes the rollout frames due now (each counts as activity of its scene).
    pub(super) fn publish_due_rollouts(&mut self) {
        for frame in self.schedule.rollouts.due(Instant::now()) {
            let idle = self.scenes.touch(&frame.scene, self.options.idle_timeout);
            self.note_idle(u64::from(idle));
            self.emit(&frame);
        }
    }

    /// Publishes a predicted frame (counted) and hands it to the live view; `arrived`, the
    /// input frame's arrival, is timed.
    pub(super) fn emit_timed(&mut self, frame: &ParticleFrame, arrived: Instant) {
        self.emit(frame);
        self.note_latencies([arrived.elapsed().as_secs_f64() * 1e6]);
    }

    /// Keeps arrival -> publication latencies (us) for the closing percentiles.
    fn note_latencies(&mut self, us: impl IntoIterator<Item = f64>) {
        if self.latencies_us.len() >= 2 * LATENCY_WINDOW {
            self.latencies_us.drain(..LATENCY_WINDOW);
        }
        self.latencies_us.extend(us);
    }

    /// Where the lander thread may publish the live frames' predictions itself: the node's
    /// publisher, unless the loop must see each of them (a live view to feed, or closed
    /// loop, whose live predictions are not published).
    pub(super) fn outlet(&self) -> Option<SharedPublisher> {
        let own = self.options.rollout.is_none() && self.view.is_none();
        own.then(|| Arc::clone(&self.publisher))
    }

    /// Counts what the lander thread published of a call, as [`Self::emit`] counts (a
    /// failed send logged once a call, with the call's last error).
    pub(super) fn count_published(&mut self, p: Published) {
        self.tally.report.published += p.sent;
        self.tally.report.dropped += p.failed;
        if let Some(e) = p.last_error {
            tracing::warn!("{e}");
            self.tally.report.last_error = e;
        }
        self.note_latencies(p.latencies_us);
    }

    /// Publishes a predicted frame (counted) and hands it to the live view.
    pub(super) fn emit(&mut self, frame: &ParticleFrame) {
        let start = Instant::now();
        let sent = lock(&self.publisher).publish(frame);
        self.times.publish += start.elapsed();
        match sent {
            Ok(()) => self.tally.report.published += 1,
            Err(e) => {
                self.tally.report.dropped += 1;
                self.tally.report.last_error = e.to_string();
                tracing::warn!("{e}");
            }
        }
        if let Some(view) = self.view.as_mut() {
            view.prediction(frame);
        }
    }

    /// Flushes the output, publishes the final status, logs the latency percentiles and
    /// returns the totals. The caller publishes the pipelined calls still landing first
    /// (`publish_landed(0)`, `batcher.rs`).
    pub(super) fn finish(mut self) -> NodeReport {
        // The loop's wall time ends here: the closing flush and reports are not the loop's.
        let loop_end = Instant::now();
        lock(&self.publisher).flush(Duration::from_secs(5));
        if let Some(view) = self.view.as_mut() {
            view.finish();
        }
        self.stamp_report();
        if let Some(p) = self.status_pub.as_mut() {
            let _ = p.publish(&self.tally.report);
        }
        log_latencies(&self.options.name, &mut self.latencies_us);
        let Evictions { full, idle } = self.evicted;
        tracing::info!(
            "{}: evicted={} scene states ({full} at --max-scenes, {idle} idle)",
            self.options.name,
            full + idle
        );
        tracing::info!("{}: {}", self.options.name, self.batches.line());
        tracing::info!("{}: {}", self.options.name, self.times.line(loop_end));
        if self.shard.is_some() {
            tracing::info!(
                "{}: shard: taken_over={} scene(s) (state started again from the next \
                 frame); {} frame(s) of other nodes' scenes passed over",
                self.options.name,
                self.adopted,
                self.others
            );
        }
        self.tally.report
    }
}
